"""The HTML report: files and budgets, order, damaged inputs, and the page in headless Chromium.

One tiny reconstruction (two classes of six objects) is shared by the module; the run writes
its report at the end (``report=true``, the default). The browser tests drive ``/usr/bin/chromium``
by its command line and are skipped, with the reason, where it is absent.
"""
from __future__ import annotations

import hashlib
import json
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

from carvi_torch.cli import main as cli_main
from carvi_torch.config import Config
from carvi_torch.executors import run
from carvi_torch.report import build_report, main as report_main
from carvi_torch.report.build import STATIC
from carvi_torch.report.cards import decode_positions
from conftest import record_settings

CHROMIUM = Path("/usr/bin/chromium")
TINY = {"procedural_instances": 6, "resolution": 20, "proposals": 4, "canvas_size": 64, "refine_iters": 30,
        "plane_size": 32, "preview": False, "progress": False, "classes": ["car", "chair"]}
#: URL-like strings the vendored three.js holds that load nothing: the XHTML namespace (an identifier) and
#: a link printed in a console warning.
VENDORED_URLS = {"http://www.w3.org/1999/xhtml", "https://github.com/mrdoob/three.js/pull/23228"}


@pytest.fixture(scope="module")
def recon(tmp_path_factory, procedural_input) -> Path:
    out = tmp_path_factory.mktemp("run")
    procedural_input(out)  # the embedded collection, generated once per session, where the run looks for it
    summary = run(Config().override({**TINY, "out": str(out)}), workers=0)  # the report is on by default
    assert all(c["reconstructed"] == 6 for c in summary["classes"].values())
    return out


def _cards(report: Path) -> tuple[dict, list[dict]]:
    """``cards.js``'s meta and cards (the file is ``carviReport.index(meta, [cards]);``)."""
    text = (report / "cards.js").read_text()
    m = re.fullmatch(r"carviReport\.index\((.*?),\n(\[.*\])\);\n", text, flags=re.S)
    assert m, text[:200]
    return json.loads(m.group(1)), json.loads(m.group(2))


def _objects(recon: Path) -> dict[str, str]:
    """annotation id -> class key, from every class's cameras.json."""
    out = {}
    for cls in ("car", "chair"):
        out.update({aid: cls for aid in json.loads((recon / cls / "cameras.json").read_text())["cameras"]})
    return out


def _tree(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).digest()
            for p in root.rglob("*") if p.is_file()}


def _chromium(url: str, shot: Path | None = None, size=(1300, 1500), extra: tuple = ()) -> str:
    """The DOM of ``url`` after its scripts ran (and a screenshot into ``shot``)."""
    if not CHROMIUM.is_file():
        pytest.skip(f"{CHROMIUM} not found (apt-get install chromium; .ci/run installs it)")
    with tempfile.TemporaryDirectory() as prof:
        cmd = [str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
               "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update",
               "--disable-sync", "--host-resolver-rules=MAP * ~NOTFOUND", f"--user-data-dir={prof}",
               "--virtual-time-budget=15000", f"--window-size={size[0]},{size[1]}", "--hide-scrollbars",
               "--dump-dom", *extra]
        if shot is not None:
            cmd.append(f"--screenshot={shot}")
        res = subprocess.run(cmd + [url], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    return res.stdout


def _dom_cards(dom: str) -> list[dict]:
    """Per card element: its attributes (annotation id, class, viewer state) and its text."""
    out = []
    for m in re.finditer(r'<div class="card[^"]*" ([^>]*)>(.*?)<dl class="stats"', dom, flags=re.S):
        attrs = dict(re.findall(r'([\w-]+)="([^"]*)"', m.group(1)))
        drawn = re.search(r'data-drawn="([0-9.]+)"', m.group(2))
        attrs["drawn"] = float(drawn.group(1)) if drawn else None
        attrs["text"] = re.sub(r"<[^>]+>", " ", m.group(2))
        out.append(attrs)
    return out


def test_reconstruct_writes_the_report_within_budget(recon):
    report = recon / "report"
    meta, cards = _cards(report)
    objects = _objects(recon)
    assert sorted(c["id"] for c in cards) == sorted(objects) and len(cards) == 12
    assert all(c["cls"] == objects[c["id"]] for c in cards)
    assert meta["sort_by"] == "quality"  # cameras.json scores every object
    cams = {aid: e for cls in ("car", "chair")
            for aid, e in json.loads((recon / cls / "cameras.json").read_text())["cameras"].items()}
    qs = [c["quality"] for c in cards]
    assert qs == sorted(qs) and all(c["quality"] == pytest.approx(cams[c["id"]]["quality"], abs=1e-4) for c in cards)
    assert all(0.3 < c["iou"] <= 1 for c in cards)
    for c in cards:
        assert not c.get("problems") and c["img"] and c["mesh"], c
        size = (report / c["img"]).stat().st_size + (report / c["mesh"]).stat().st_size
        assert size <= 200_000, (c["id"], size)
        for link in c["files"].values():  # the card's links resolve to the run's files
            assert (report / link).resolve().is_file()
    assert (report / "index.html").is_file() and len(list((report / "classes").glob("*.png"))) == 2


def _voxel_boxes(shape, occupancy, T) -> np.ndarray:
    """Brute force: every occupied voxel's box (index +- 0.5, its 8 corners through ``T``), filled."""
    sil = np.zeros(shape, bool)
    ys, xs = np.arange(shape[0])[:, None], np.arange(shape[1])[None, :]
    corners = np.array(np.meshgrid([-0.5, 0.5], [-0.5, 0.5], [-0.5, 0.5], indexing="ij")).reshape(3, -1)
    for idx in np.argwhere(occupancy):
        p = T[:2, :3] @ (idx[:, None] + corners) + T[:2, 3:]
        sil |= (xs > p[0].min()) & (xs < p[0].max()) & (ys > p[1].min()) & (ys < p[1].max())
    return sil


def test_overlay_silhouette_is_the_voxels_projection(recon):
    """The card's IoU of mask and silhouette against independent references: the voxel boxes filled one
    by one, the mask from pycocotools; and the mesh file's outline (its faces filled, z dropped) agrees."""
    from pycocotools.coco import COCO
    from skimage.draw import polygon

    _, cards = _cards(recon / "report")
    coco = COCO(str(recon / "input" / "annotations.json"))
    for c in cards[:3]:
        mask = coco.annToMask(coco.anns[int(c["id"])]).astype(bool)
        z = np.load(recon / c["cls"] / "voxels" / f"{c['id']}.npz")
        sil = _voxel_boxes(mask.shape, z["occupancy"], z["voxel_to_camera"])
        assert abs((sil & mask).sum() / (sil | mask).sum() - c["iou"]) < 0.01, c["id"]
        m = trimesh.load(recon / c["cls"] / "meshes" / f"{c['id']}.ply", process=False)
        outline = np.zeros_like(mask)
        for tri in m.vertices[m.faces][:, :, :2]:
            rr, cc = polygon(tri[:, 1], tri[:, 0], mask.shape)
            outline[rr, cc] = True
        assert (outline & sil).sum() / (outline | sil).sum() > 0.7, c["id"]  # the mesh lies half a voxel inside


def test_mesh_data_decodes_to_the_mesh(recon):
    """Decoded positions lie on the original mesh's surface (within a voxel) and span its bounding box."""
    _, cards = _cards(recon / "report")
    c = cards[-1]
    text = (recon / "report" / c["mesh"]).read_text()
    key, data = re.fullmatch(r'carviReport\.mesh\(("[^"]+"),(.*)\);\n', text, flags=re.S).groups()
    assert json.loads(key) == c["key"]
    data = json.loads(data)
    v = decode_positions(data)
    m = trimesh.load(recon / c["cls"] / "meshes" / f"{c['id']}.ply", process=False)
    voxel = float(np.linalg.norm(np.load(recon / c["cls"] / "voxels" / f"{c['id']}.npz")["voxel_to_camera"][:3, :3],
                                 axis=0).max())
    _, dist, _ = trimesh.proximity.closest_point(m, v)
    assert dist.max() < voxel, (dist.max(), voxel)
    assert np.allclose(v.min(0), m.bounds[0], atol=voxel) and np.allclose(v.max(0), m.bounds[1], atol=voxel)
    idx = np.frombuffer(__import__("base64").b64decode(data["index"]), dtype="<u2")
    assert len(idx) == 3 * c["faces"] and idx.max() < len(v)


def test_quality_orders_the_cards_and_damaged_files_are_named(recon, tmp_path):
    """``quality`` in cameras.json orders the cards (ascending); a missing mesh, damaged voxels and an
    unreadable cameras.json each give a visible reason, and the command writes only under --out."""
    run = tmp_path / "run"
    shutil.copytree(recon, run, ignore=shutil.ignore_patterns("report"))
    cams = json.loads((run / "car" / "cameras.json").read_text())
    ids = list(cams["cameras"])
    for i, aid in enumerate(ids):
        cams["cameras"][aid]["quality"] = [0.9, 0.1, 0.5, 0.7, 0.3, 0.2][i]
    (run / "car" / "cameras.json").write_text(json.dumps(cams))
    (run / "car" / "meshes" / f"{ids[0]}.ply").unlink()
    (run / "car" / "voxels" / f"{ids[2]}.npz").write_bytes(b"not an npz")
    (run / "chair" / "cameras.json").write_text("{broken")
    summary = json.loads((run / "summary.json").read_text())
    summary["classes"]["car"]["failures"] = [{"annotation_id": 999, "source": "x.xml", "stage": "load",
                                              "reason": "mask <empty> & no keypoints"}]
    (run / "summary.json").write_text(json.dumps(summary))
    before = _tree(run)
    assert cli_main(["report", "--recon", str(run), "--out", str(run / "rep"), "--quiet", "--per-page", "4"]) == 0
    after = _tree(run)
    assert {k: v for k, v in after.items() if not k.startswith("rep/")} == before
    meta, cards = _cards(run / "rep")
    assert meta["sort_by"] == "quality" and meta["per_page"] == 4
    car = [c for c in cards if c["cls"] == "car"]
    # skipped first, then damaged files, then by quality
    assert [c["id"] for c in car] == ["999", ids[2], ids[0], ids[1], ids[5], ids[4], ids[3]]
    assert car[0]["skipped"] == "mask <empty> & no keypoints"
    assert "annotation not in the input" in car[0]["problems"][0]
    assert "voxels unreadable" in car[1]["problems"][0] and "no mesh file" in car[2]["problems"][0]
    assert not any(c["cls"] == "chair" for c in cards)
    page = (run / "rep" / "index.html").read_text()
    assert "chair/cameras.json unreadable" in page
    assert "999 (x.xml): load: mask &lt;empty&gt; &amp; no keypoints" in page
    assert report_main(["--recon", str(run), "--out", str(run), "--quiet"]) == 2  # never over the run's own files
    assert report_main(["--recon", str(tmp_path / "nothing"), "--quiet"]) == 2
    assert not (tmp_path / "nothing").exists()


class _BrokenPool:
    """An executor whose every job fails as when its worker process died."""

    def submit(self, fn, *args):
        from concurrent.futures import Future
        from concurrent.futures.process import BrokenProcessPool

        future = Future()
        future.set_exception(BrokenProcessPool("the worker process died"))
        return future


def test_mesh_scripts_made_in_a_pool_give_the_same_report(recon, tmp_path):
    """A run hands the report's mesh scripts to its writer processes (``start_report(pool=...)``) while it draws the
    rest: the same files, byte for byte, as ``build_report`` in one process, a damaged and a missing mesh's reasons
    included; a pool whose processes fail, or that refuses the jobs, has the scripts made here, the same again."""
    import multiprocessing as mp

    from carvi_torch.report.build import start_report
    from carvi_torch.runtime import LeanProcessPool, start_method

    run = tmp_path / "run"
    shutil.copytree(recon, run, ignore=shutil.ignore_patterns("report"))
    ids = list(json.loads((run / "car" / "cameras.json").read_text())["cameras"])
    (run / "car" / "meshes" / f"{ids[0]}.ply").unlink()
    (run / "car" / "meshes" / f"{ids[1]}.ply").write_bytes(b"ply\nnot a mesh")
    build_report(run, run / "here", workers=0)
    with LeanProcessPool(1, mp_context=mp.get_context(start_method())) as pool:
        pending = start_report(run, run / "pooled", pool=pool)
        pending.finish()
    start_report(run, run / "broken", pool=_BrokenPool()).finish()
    pool = LeanProcessPool(1, mp_context=mp.get_context(start_method()))
    pool.shutdown()
    start_report(run, run / "shut", pool=pool).finish()  # a pool that refuses every job
    here = _tree(run / "here")
    assert _tree(run / "pooled") == here and _tree(run / "broken") == here and _tree(run / "shut") == here
    car = {c["id"]: c for c in _cards(run / "here")[1] if c["cls"] == "car"}
    assert "no mesh file" in car[ids[0]]["problems"][0] and "mesh unreadable" in car[ids[1]]["problems"][0]
    assert all(car[i].get("faces") for i in ids[2:])


def test_a_class_meshes_in_an_earlier_format_get_their_3d_view_and_link(recon, tmp_path):
    """A run whose ``mesh_format`` changed after a class was made keeps that class's meshes in the earlier format: its
    cards show and link the file the export takes (:func:`~carvi_torch.io.layout.object_mesh`), not "no mesh file"."""
    from carvi_torch.config import read_run_config

    run = tmp_path / "run"
    shutil.copytree(recon, run, ignore=shutil.ignore_patterns("report"))
    (run / "config.yaml").write_text(read_run_config(run / "config.yaml").override(["mesh_format=obj"]).to_yaml())
    assert report_main(["--recon", str(run), "--out", str(tmp_path / "rep"), "--quiet"]) == 0
    _, cards = _cards(tmp_path / "rep")
    assert cards and all(c.get("mesh") and not c.get("problems") for c in cards), cards[0]
    assert all(c["files"]["mesh"].endswith(f"meshes/{c['id']}.ply") for c in cards)


def test_the_page_says_when_objects_were_made_with_other_settings(recon, tmp_path):
    """A run whose summary records objects made with other settings than its config.yaml's: the page's header says
    which, in one escaped line, with how many objects their voxels files say were made so; a run without the record
    has no such line."""
    run = tmp_path / "run"
    shutil.copytree(recon, run, ignore=shutil.ignore_patterns("report"))
    assert report_main(["--recon", str(run), "--out", str(tmp_path / "same"), "--quiet"]) == 0
    assert "other settings" not in (tmp_path / "same" / "index.html").read_text()
    summary = json.loads((run / "summary.json").read_text())
    summary["resumed_from_other_settings"] = {"carve.resolution": [16, 24], "<b>": ["x", "y"]}
    (run / "summary.json").write_text(json.dumps(summary))
    assert report_main(["--recon", str(run), "--out", str(tmp_path / "rep"), "--quiet"]) == 0
    page = (tmp_path / "rep" / "index.html").read_text()
    line = re.search(r"<p class=warn>(.*?)</p>", page).group(1)
    assert "carve.resolution 16 then 24; &lt;b&gt; x then y" in line and "<b>" not in page
    assert "; 0 of its 12 objects by their voxels files;" in line
    record_settings(sorted((run / "chair" / "voxels").glob("*.npz"))[:1], carve__resolution=16)
    sorted((run / "car" / "voxels").glob("*.npz"))[0].unlink()  # an object without files is not counted
    assert report_main(["--recon", str(run), "--out", str(tmp_path / "rep2"), "--quiet"]) == 0
    line = re.search(r"<p class=warn>(.*?)</p>", (tmp_path / "rep2" / "index.html").read_text()).group(1)
    assert "; 1 of its 11 objects by their voxels files;" in line


def test_no_network_reference_and_vendored_files_intact(recon):
    for p in (recon / "report").rglob("*"):
        if p.suffix in (".jpg", ".png") or p.name in ("LICENSE.three.txt", "VENDOR.md") or not p.is_file():
            continue
        urls = set(re.findall(r"https?://[^\s\"'<>)]+", p.read_text(errors="replace")))
        allowed = VENDORED_URLS if p.name == "three.min.js" else set()
        assert urls <= allowed, (p.name, urls - allowed)
    notes = (STATIC / "vendor" / "VENDOR.md").read_text()
    for name in ("three.min.js", "OrbitControls.js"):
        digest = hashlib.sha256((STATIC / "vendor" / name).read_bytes()).hexdigest()
        assert digest in notes, name
        assert (recon / "report" / "assets" / name).read_bytes() == (STATIC / "vendor" / name).read_bytes()


def test_page_in_chromium_cards_viewers_and_screenshot(recon, tmp_path):
    from PIL import Image

    shot = tmp_path / "shot.png"
    dom = _chromium((recon / "report" / "index.html").as_uri(), shot)
    assert re.search(r'<body[^>]* data-ready="1"', dom), dom[:500]
    cards = _dom_cards(dom)
    assert sorted(c["data-annotation-id"] for c in cards) == sorted(_objects(recon))
    assert all(c["data-viewer"] == "ok" and c["drawn"] > 0.01 for c in cards), [
        (c["data-annotation-id"], c["data-viewer"], c["drawn"]) for c in cards]
    px = np.asarray(Image.open(shot).convert("L"), dtype=np.float64)
    assert px.std() > 20 and (px < 128).mean() > 0.01  # not blank: text, plots, overlays


def test_page_in_chromium_filter_pages_and_reasons(recon, tmp_path):
    """The class filter and the page come from the URL; a card whose mesh data is gone says why, and
    the page is still ready."""
    run = tmp_path / "run"
    shutil.copytree(recon, run, ignore=shutil.ignore_patterns("report"))
    build_report(run, run / "rep", per_page=4, workers=2)  # worker processes make the same cards
    meta, order = _cards(run / "rep")
    assert order == _cards(recon / "report")[1] and meta["per_page"] == 4
    car = [c for c in order if c["cls"] == "car"]
    (run / "rep" / car[4]["mesh"]).unlink()
    dom = _chromium((run / "rep" / "index.html").as_uri() + "#class=car&page=2")
    assert re.search(r'<body[^>]* data-ready="1"', dom) and "page 2 of 2" in dom
    cards = _dom_cards(dom)
    assert [c["data-annotation-id"] for c in cards] == [c["id"] for c in car[4:]]
    assert all(c["data-class"] == "car" for c in cards)
    assert cards[0]["data-viewer"] == "failed" and "mesh data missing" in cards[0]["text"]
    assert cards[1]["data-viewer"] == "ok"


def test_class_link_is_url_encoded():
    """A class key with '%' or '&' still links to its own cards (the page decodes the hash)."""
    from carvi_torch.report.page import class_panel_html

    html = class_panel_html({"objects": 1}, "100%&x", "100%&x", None, None)
    assert "href='#class=100%25%26x&amp;page=1'" in html


def test_page_with_a_malformed_class_in_the_url_shows_every_class(recon):
    """'#class=100%&page=1' (a bare '%'): no class filter, every card, and the page is still ready."""
    dom = _chromium((recon / "report" / "index.html").as_uri() + "#class=100%&page=1")
    assert re.search(r'<body[^>]* data-ready="1"', dom), dom[:500]
    assert sorted(c["data-annotation-id"] for c in _dom_cards(dom)) == sorted(_objects(recon))


def test_page_without_webgl_still_shows_every_card(recon):
    """No WebGL: every 3D view says so, the overlays stay, and the page is still ready."""
    dom = _chromium((recon / "report" / "index.html").as_uri() + "#class=chair", extra=("--disable-webgl",))
    assert re.search(r'<body[^>]* data-ready="1"', dom)
    cards = _dom_cards(dom)
    assert len(cards) == 6 and all(c["data-class"] == "chair" for c in cards)
    assert all(c["data-viewer"] == "failed" and "WebGL unavailable" in c["text"] for c in cards)
    assert dom.count('class="overlay"') == 6


def test_overlay_refuses_an_annotation_the_file_changed_since_the_run(tmp_path):
    """An annotation id whose class or ``source`` in the input file differs from the run's ``cameras.json``
    entry is another object now: its card draws no overlay and says what the id is now."""
    from carvi_torch.report.build import _context
    from carvi_torch.report.cards import Card, ClassView, _overlay
    from carvi_torch.report.inputs import ObjectInputs

    poly = [[2.0, 2.0, 12.0, 2.0, 12.0, 12.0, 2.0, 12.0]]
    data = tmp_path / "annotations.json"
    data.write_text(json.dumps({
        "images": [{"id": 1, "width": 16, "height": 16, "file_name": "none.png"}],
        "categories": [{"id": 1, "name": "car", "keypoints": ["a"]}, {"id": 2, "name": "chair", "keypoints": ["a"]}],
        "annotations": [{"id": i, "image_id": 1, "category_id": c, "segmentation": poly, "area": 100.0,
                         "bbox": [2, 2, 10, 10], "keypoints": [5, 5, 2], "num_keypoints": 1, **extra}
                        for i, c, extra in [(7, 2, {"source": "b.png"}), (8, 1, {"source": "a.png"}), (9, 1, {})]]}))
    ctx = _context(tmp_path / "run", tmp_path / "rep", data, "ply", 100)
    car = ClassView("car", [])
    cards = {}
    for aid, src in [("7", "a.png"), ("8", "c.png"), ("9", None)]:
        cards[aid] = Card(id=aid, cls="car", key=f"car/{aid}")
        _overlay(ctx, car, ObjectInputs(aid, aid, source=src), cards[aid], f"objects/car/{aid}.jpg")
    assert cards["7"].problems == ["annotation 7 is now chair b.png, not the run's: no overlay"]
    assert cards["8"].problems == ["annotation 8 is now car a.png, not the run's: no overlay"]
    assert cards["7"].img is None and cards["8"].img is None
    assert cards["9"].img == "objects/car/9.jpg" and "voxels missing" in cards["9"].problems[0]  # the same object


@pytest.mark.parametrize("option", [["--per-page", "0"], ["--per-page", "-3"], ["--workers", "-1"]])
def test_report_refuses_a_count_out_of_range(option, tmp_path, capsys):
    """``--per-page`` below 1 and ``--workers`` below 0 are argparse errors (exit 2), not quietly made 1 and 0."""
    with pytest.raises(SystemExit) as e:
        report_main(["--recon", str(tmp_path), "--quiet", *option])
    assert e.value.code == 2 and f"argument {option[0]}: expected an integer >= " in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_report_never_writes_through_a_link_in_out(recon, tmp_path, capsys):
    """A symbolic link among the report's entries in --out (a file's name, a folder, one deep in ``objects/``)
    is refused with one ``error:`` line naming it (exit 2): nothing is written, its target least of all. A
    temporary file left by a killed report does not make --out foreign."""
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "precious.txt").write_text("precious")
    rep = tmp_path / "rep"
    rep.mkdir()
    (rep / "index.html").symlink_to(victim / "precious.txt")
    (rep / "assets").symlink_to(victim)
    argv = ["--recon", str(recon), "--out", str(rep), "--quiet", "--workers", "0"]
    for name in ("assets", "index.html", "objects/car/1.jpg"):
        if name == "objects/car/1.jpg":
            (rep / "objects" / "car").mkdir(parents=True)
            (rep / name).symlink_to(victim / "precious.txt")
        before = sorted(p.relative_to(rep).as_posix() for p in rep.rglob("*"))
        assert report_main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and err.count("\n") == 1 and f"'{name}' is a symbolic link" in err, err
        assert sorted(p.relative_to(rep).as_posix() for p in rep.rglob("*")) == before
        assert [p.name for p in victim.iterdir()] == ["precious.txt"]
        assert (victim / "precious.txt").read_text() == "precious"
        (rep / name).unlink()
    (rep / ".index.html.k3j_x2.tmp").write_text("<html")  # a report killed while writing index.html
    assert report_main(argv) == 0
    assert (rep / "index.html").is_file() and not (rep / "index.html").is_symlink()
    assert (victim / "precious.txt").read_text() == "precious" and len(list(victim.iterdir())) == 1


def test_a_linked_report_folder_of_the_run_is_refused_by_default(recon, tmp_path, capsys):
    """``RECON/report`` a symbolic link (to a folder outside the run) and no --out: one ``error:`` line naming it,
    exit 2, nothing written through it (reconstruct refuses that link too); given as --out, the link is the folder
    the user named."""
    run = tmp_path / "run"
    shutil.copytree(recon, run, ignore=shutil.ignore_patterns("report"))
    (tmp_path / "elsewhere").mkdir()
    (run / "report").symlink_to("../elsewhere")
    capsys.readouterr()
    assert report_main(["--recon", str(run), "--quiet", "--workers", "0"]) == 2
    err = capsys.readouterr().err
    assert err == (f"error: {run / 'report'} is a symbolic link: the report writes only inside the run's folder; "
                   "remove the link or give --out (nothing was written)\n"), err
    assert not any((tmp_path / "elsewhere").iterdir())
    assert report_main(["--recon", str(run), "--out", str(run / "report"), "--quiet", "--workers", "0"]) == 0
    assert (tmp_path / "elsewhere" / "index.html").is_file()


def test_writes_replace_a_link_and_refuse_a_linked_folder(tmp_path):
    """Every write of the report (:func:`~carvi_torch.io.outputs.write_within`) replaces a link standing at the
    file's name (its target untouched) and refuses a link where a folder is, also a link planted after the
    command's check: a card written into a linked folder fails with the reason, nothing lands in the target."""
    from carvi_torch.io.outputs import folder_within, write_within
    from carvi_torch.report.cards import CardContext, ClassView, make_card
    from carvi_torch.report.inputs import ObjectInputs

    victim, root = tmp_path / "victim", tmp_path / "rep"
    victim.mkdir()
    root.mkdir()
    (victim / "precious.txt").write_text("precious")
    (root / "a.txt").symlink_to(victim / "precious.txt")
    write_within(root, "a.txt", b"mine", sync=False)
    assert not (root / "a.txt").is_symlink() and (root / "a.txt").read_text() == "mine"
    (root / "objects").mkdir()
    (root / "objects" / "car").symlink_to(victim)
    with pytest.raises(NotADirectoryError, match="symbolic link"):
        write_within(root, "objects/car/b.txt", b"mine")
    (root / "file").write_text("x")
    with pytest.raises(NotADirectoryError, match="a file"):
        folder_within(root, "file/sub")
    with pytest.raises(ValueError):
        folder_within(root, "../victim")
    mesh = trimesh.creation.box()
    run = tmp_path / "run"
    (run / "car" / "meshes").mkdir(parents=True)
    mesh.export(run / "car" / "meshes" / "7.ply")
    ctx = CardContext(recon=run, out=root, anns={}, images={}, coco=None, data=None, data_problem="no data")
    card = make_card(ctx, ClassView("car", []), ObjectInputs("7", "7"), "car")
    assert card.mesh is None and "card failed (NotADirectoryError" in card.problems[-1], card
    assert sorted(p.name for p in victim.iterdir()) == ["precious.txt"]
    assert (victim / "precious.txt").read_text() == "precious"


def test_object_missing_from_cameras_json_gets_a_card(recon, tmp_path):
    """An annotated object that summary.json counts reconstructed but its class's cameras.json lacks gets a
    card (first, with the reason, its overlay and mesh), and the class panel says how many are missing."""
    run = tmp_path / "run"
    shutil.copytree(recon, run, ignore=shutil.ignore_patterns("report"))
    cams = json.loads((run / "chair" / "cameras.json").read_text())
    gone = list(cams["cameras"])[2]
    del cams["cameras"][gone]
    (run / "chair" / "cameras.json").write_text(json.dumps(cams))
    rep = build_report(run, run / "rep", workers=0)
    _, cards = _cards(run / "rep")
    assert rep.cards == 12 and sorted(c["id"] for c in cards) == sorted(_objects(recon))
    chair = [c for c in cards if c["cls"] == "chair"]
    assert chair[0]["id"] == gone, chair[0]
    assert chair[0]["problems"] == ["camera missing from cameras.json (summary.json counts the object in its "
                                    "class)"]
    assert chair[0]["img"] and chair[0]["mesh"] and 0.3 < chair[0]["iou"] <= 1
    assert "chair/cameras.json and the failures of the class name 5 of the 6 objects summary.json counts" in (
        run / "rep" / "index.html").read_text()


def _edit(path: Path, edit) -> None:
    content = json.loads(path.read_text())
    edit(content)
    path.write_text(json.dumps(content))


@pytest.mark.parametrize("edits, notes", [
    ({"car/cameras.json": lambda c: c.update(cameras=[1]),
      "chair/cameras.json": lambda c: c.update(mean_shape=[1, 2]),
      "summary.json": lambda s: (s.update(input_problems=5), s["classes"]["car"].update(failures=5),
                                 s["classes"]["chair"].update(warnings=7))},
     ["summary.json: 'input_problems' is 5, not a list",
      "summary.json class car: 'failures' is 5, not a list",
      "summary.json class chair: 'warnings' is 7, not a list",
      "car/cameras.json: 'cameras' is [1], not an object of annotation id -> entry",
      "chair/cameras.json: mean_shape is [1, 2], not an object of keypoint name -> 3 numbers"]),
    ({"car/cameras.json": lambda c: c["mean_shape"].update(left_back_trunk="x"),
      "chair/cameras.json": lambda c: c.update(shape_groups=[5]),
      "summary.json": lambda s: s["classes"]["car"].update(seconds="x")},
     ["summary.json class car: 'seconds' is 'x', not an object",
      "car/cameras.json: mean_shape 'left_back_trunk' is 'x', not 3 finite numbers",
      "chair/cameras.json: 'shape_groups' is [5], not a list of objects with a mean_shape"]),
], ids=["cameras-list", "mean-shape-junk"])
def test_hand_edited_parts_of_the_wrong_type_are_read_as_absent(recon, tmp_path, caplog, edits, notes):
    """Parts of cameras.json and summary.json of the wrong type (a hand-edited file): each is one warning line naming
    the file and read as absent, the class panel says so, and every object still gets its card."""
    from html import escape

    run = tmp_path / "run"
    shutil.copytree(recon, run, ignore=shutil.ignore_patterns("report"))
    for rel, edit in edits.items():
        _edit(run / rel, edit)
    with caplog.at_level("WARNING", logger="carvi_torch"):
        rep = build_report(run, tmp_path / "rep", workers=0)
    notes = [f"{n}; read as absent" for n in notes]
    assert [r.getMessage() for r in caplog.records if r.getMessage().endswith("read as absent")] == [
        f"report: {n}" for n in notes]
    page = (tmp_path / "rep" / "index.html").read_text()
    assert all(escape(n) in page for n in notes if "class" in n or "cameras.json" in n)
    assert rep.cards == 12


def test_photo_is_read_only_beside_the_annotations(tmp_path):
    """An image entry's ``file_name`` is read relative to the annotation file's folder or the folder above it;
    an absolute name, one climbing farther, a missing file, a folder, a pipe, a file that is no image and an
    image of another size give no photo (the overlay on white), never an error."""
    import os

    from PIL import Image

    from carvi_torch.report.cards import CardContext, _photo

    ds = tmp_path / "ds"
    (ds / "ann").mkdir(parents=True)
    (ds / "img").mkdir()
    pixels = np.full((12, 16, 3), 200, np.uint8)
    for p in (ds / "ann" / "in.png", ds / "img" / "up.png", tmp_path / "far.png"):
        Image.fromarray(pixels).save(p)
    Image.fromarray(pixels[:6]).save(ds / "ann" / "small.png")
    (ds / "ann" / "text.png").write_text("not an image")
    (ds / "ann" / "dir.png").mkdir()
    os.mkfifo(ds / "ann" / "fifo.png")
    names = {"in.png": True, "../img/up.png": True, "sub/../in.png": True, str(tmp_path / "far.png"): False,
             "../../far.png": False, "../img/../../far.png": False, "small.png": False, "text.png": False,
             "dir.png": False, "fifo.png": False, "missing.png": False, None: False, 5: False}
    images = {i: {"id": i, "file_name": name} for i, name in enumerate(names)}
    ctx = CardContext(recon=tmp_path, out=tmp_path / "rep", anns={}, images=images, coco=None,
                      data=ds / "ann" / "annotations.json")
    for i, (name, read) in enumerate(names.items()):
        photo = _photo(ctx, {"image_id": i}, (12, 16))
        assert (photo is not None) == read, name
        if read:
            assert photo.shape == (12, 16, 3) and np.allclose(photo, 200 / 255)
