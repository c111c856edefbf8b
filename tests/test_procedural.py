"""Tests of carvi_torch.synthetic.procedural: watertight instances, keypoints, variation, collection."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from carvi_torch.synthetic.meshes import infer_flip_pairs
from carvi_torch.synthetic.procedural import CATEGORIES, make_collection, make_instance, write_default_collection
from carvi_torch.synthetic.render import seed_generator

N_PER_CLASS = 4


@pytest.fixture(scope="module")
def instances():
    return {c: [make_instance(c, seed_generator(7, c, i), name=f"{c}{i:03d}") for i in range(N_PER_CLASS)]
            for c in CATEGORIES}


def test_categories():
    assert set(CATEGORIES) >= {"car", "aeroplane", "chair", "bottle"}
    with pytest.raises(ValueError, match="category"):
        make_instance("unicorn", torch.Generator())


@pytest.mark.parametrize("category", CATEGORIES)
def test_instances_are_watertight_single_outward_meshes(instances, category):
    for m in instances[category]:
        assert m.vertices.dtype == torch.float32 and m.faces.dtype == torch.long
        tm = trimesh.Trimesh(m.vertices.double().numpy(), m.faces.numpy(), process=False)
        assert tm.is_watertight, m.name
        assert tm.is_winding_consistent, m.name
        assert tm.volume > 0, m.name  # outward normals
        assert len(tm.split(only_watertight=False)) == 1, m.name  # one connected solid
        # PASCAL3D+ normalisation: centred bounding box with a unit diagonal
        lo, hi = tm.bounds
        np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-6)
        assert abs(np.linalg.norm(hi - lo) - 1) < 1e-6


@pytest.mark.parametrize("category", CATEGORIES)
def test_keypoints_on_surface_and_named_in_pairs(instances, category):
    for m in instances[category]:
        assert len(m.keypoint_names) >= 8
        pairs = infer_flip_pairs(m.keypoint_names)
        assert len(pairs) >= 2
        tm = trimesh.Trimesh(m.vertices.double().numpy(), m.faces.numpy(), process=False)
        _, dist, _ = trimesh.proximity.closest_point(tm, m.keypoints.double().numpy())
        assert dist.max() < 0.02, (m.name, dict(zip(m.keypoint_names, dist.round(4))))  # within one grid cell
        # left is -x, right is +x (PASCAL3D+ naming), mirror pairs are mirror images
        for i, j in pairs:
            a, b = m.keypoints[i], m.keypoints[j]
            left, right = (a, b) if "left" in m.keypoint_names[i] else (b, a)
            assert left[0] < 0 < right[0]
            torch.testing.assert_close(left * torch.tensor([-1.0, 1, 1]), right, atol=2e-3, rtol=0)


def test_object_frame_orientation(instances):
    """+z up and front towards -y, as PASCAL3D+."""
    for car in instances["car"]:
        k = dict(zip(car.keypoint_names, car.keypoints))
        assert k["left_front_wheel"][1] < k["left_back_wheel"][1]
        assert k["upper_left_windshield"][2] > k["left_front_wheel"][2]
    for plane in instances["aeroplane"]:
        k = dict(zip(plane.keypoint_names, plane.keypoints))
        assert k["noselanding"][1] < k["tail"][1] and k["rudder_upper"][2] > k["rudder_lower"][2]
    for chair in instances["chair"]:
        k = dict(zip(chair.keypoint_names, chair.keypoints))
        assert k["back_upper_left"][2] > k["seat_upper_left"][2] > k["leg_upper_left"][2]
        assert k["seat_lower_left"][1] < k["seat_upper_left"][1]
    for bottle in instances["bottle"]:
        k = dict(zip(bottle.keypoint_names, bottle.keypoints))
        assert k["mouth"][2] > k["body"][2] > k["bottom"][2]


def test_bottle_is_rotationally_symmetric(instances):
    for m in instances["bottle"]:
        v = m.vertices.double()
        r = v[:, :2].norm(dim=1)
        # radius as a function of height: vertices in the same thin slice share one radius (up to the grid)
        z = v[:, 2]
        for zc in torch.linspace(z.min() + 0.05, z.max() - 0.05, 7):
            sl = (z - zc).abs() < 0.004
            if sl.sum() > 8:
                assert (r[sl].max() - r[sl].min()).item() < 0.02


def test_intra_class_variation(instances):
    for c, ms in instances.items():
        # normalised keypoint layouts differ between instances
        layouts = torch.stack([m.keypoints for m in ms])
        spread = (layouts - layouts.mean(dim=0)).norm(dim=-1).mean().item()
        assert spread > 0.01, c
        # so do the shapes: volumes differ by more than a few percent
        vols = [trimesh.Trimesh(m.vertices.double().numpy(), m.faces.numpy(), process=False).volume for m in ms]
        assert (max(vols) - min(vols)) / max(vols) > 0.05, (c, vols)


def test_determinism():
    a = make_instance("chair", seed_generator(1, "x"))
    b = make_instance("chair", seed_generator(1, "x"))
    c = make_instance("chair", seed_generator(2, "x"))
    assert torch.equal(a.vertices, b.vertices) and torch.equal(a.faces, b.faces)
    assert torch.equal(a.keypoints, b.keypoints)
    assert a.vertices.shape != c.vertices.shape or not torch.equal(a.vertices, c.vertices)
    # an instance does not depend on how many are asked for
    small = make_collection(2, seed=4, categories=["car"])
    big = make_collection(3, seed=4, categories=["car"])
    assert [m.name for m in small] == ["car000", "car001"]
    assert torch.equal(small[1].vertices, big[1].vertices)
    with pytest.raises(ValueError, match="categories"):
        make_collection(2, categories=["car", "ship"])


def test_write_default_collection_small(tmp_path):
    summary = write_default_collection(tmp_path, instances_per_class=3, seed=0)
    assert summary["images"] == 3 * len(CATEGORIES) and summary["categories"] == sorted(CATEGORIES)
    data = json.loads((tmp_path / "annotations.json").read_text())
    cats = {c["name"]: c for c in data["categories"]}
    assert cats["bottle"]["symmetry"] == "rotational" and cats["car"]["symmetry"] == "none"
    assert all(len(c["flip_pairs"]) >= 2 for c in cats.values())
    # VOC-like: every instance is its own object, one photograph each
    assert len({a["object_id"] for a in data["annotations"]}) == len(data["annotations"])
    assert all(a["num_keypoints"] > 0 and a["area"] > 100 for a in data["annotations"])
    gt = json.loads((tmp_path / "gt.json").read_text())
    assert len(gt["annotations"]) == len(data["annotations"])
    assert all((tmp_path / g["mesh"]).is_file() for g in gt["annotations"].values())


def test_default_collection_is_generated_again_for_other_settings(tmp_path):
    """A rerun into the same folder with another ``procedural_instances`` or ``seed`` gets the collection those
    settings make (not the one already there); the same settings reuse it."""
    from carvi_torch.synthetic.procedural import GENERATION_RECORD, default_collection, generation_settings

    def annotations(n, seed):
        said = []
        ann, _ = default_collection(tmp_path, n, seed, log=said.append)
        data = json.loads(ann.read_text())
        gt = json.loads((tmp_path / "gt.json").read_text())
        assert len(gt["annotations"]) == len(data["annotations"])
        return data, said

    first, said = annotations(1, 0)
    assert len(first["annotations"]) == len(CATEGORIES) and len(said) == 1
    assert json.loads((tmp_path / GENERATION_RECORD).read_text()) == generation_settings(1, 0)
    again, said = annotations(1, 0)
    assert again == first and said == []
    more, said = annotations(2, 0)
    assert len(more["annotations"]) == 2 * len(CATEGORIES) and "instances_per_class 1 there, 2 now" in said[0]
    other, said = annotations(2, 3)
    assert other["info"]["seed"] == 3 and [a["keypoints"] for a in other["annotations"]] != \
        [a["keypoints"] for a in more["annotations"]]
    assert json.loads((tmp_path / GENERATION_RECORD).read_text()) == generation_settings(2, 3)
    assert len(list((tmp_path / "meshes").iterdir())) == 2 * len(CATEGORIES)


def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_default_collection_is_kept_in_the_cache(tmp_path, monkeypatch):
    """Generated once per settings and code, then copied from ``$CARVI_TORCH_CACHE/collections``: a hit gives the
    same files byte for byte (so the same arrays); other settings or other code are another key (a miss); a
    damaged, truncated, tampered or others-writable entry is not used but generated again and replaced, never a
    crash; a cache that cannot be written leaves the collection as without one."""
    from carvi_torch.synthetic import cache
    from carvi_torch.synthetic.procedural import default_collection, generation_settings

    monkeypatch.setenv("CARVI_TORCH_CACHE", str(tmp_path / "cache"))

    def collection(name, seed=0):
        said = []
        default_collection(tmp_path / name, 1, seed, log=said.append)
        assert len(said) == 1
        return _files(tmp_path / name), said[0]

    first, said = collection("a")
    assert said.startswith("generating")
    key = cache.collection_key(generation_settings(1, 0))
    entry = cache.entry_path(key)
    assert entry.is_file() and oct(entry.parent.stat().st_mode & 0o777) == "0o700"
    kept = cache.load_files(key)
    assert kept == {n: b for n, b in first.items() if n != "procedural.json"}
    again, said = collection("b")
    assert said.startswith("copying") and again == first
    other, said = collection("c", seed=1)
    assert said.startswith("generating") and other != first
    assert cache.collection_key(generation_settings(1, 1)) != key
    monkeypatch.setattr(cache, "_source_digest", lambda: "other code")
    assert cache.collection_key(generation_settings(1, 0)) != key
    monkeypatch.undo()
    monkeypatch.setenv("CARVI_TORCH_CACHE", str(tmp_path / "cache"))
    good = entry.read_bytes()
    blob = np.frombuffer(good, np.uint8).copy()
    with np.load(entry) as z:
        tampered = {k: z[k] for k in z.files}
    tampered["blob"] = tampered["blob"].copy()
    tampered["blob"][0] ^= 1
    for i, damage in enumerate((b"junk", good[:len(good) // 2], None, "others")):
        if damage is None:
            np.savez(entry, **tampered)
        elif damage == "others":
            entry.write_bytes(blob.tobytes())
            entry.chmod(0o666)
        else:
            entry.write_bytes(damage)
        assert cache.load_files(key) is None, damage
        rebuilt, said = collection(f"d{i}")
        assert said.startswith("generating") and rebuilt == first
        assert entry.read_bytes() == good and cache.load_files(key) is not None
    monkeypatch.setenv("CARVI_TORCH_CACHE", str(tmp_path / "a" / "annotations.json"))  # a file: nothing written
    unkept, said = collection("e")
    assert said.startswith("generating") and unkept == first


def test_collection_cache_keeps_the_most_recently_used(tmp_path, monkeypatch):
    """At most ``KEEP`` entries; a hit counts as a use."""
    import os
    import time

    from carvi_torch.synthetic import cache

    monkeypatch.setenv("CARVI_TORCH_CACHE", str(tmp_path))
    monkeypatch.setattr(cache, "KEEP", 2)
    for i, key in enumerate(("k1", "k2")):
        cache.store_files(key, {"annotations.json": b"{}", "meshes/m.ply": bytes([i])})
        os.utime(cache.entry_path(key), (time.time() - 100 + i, time.time() - 100 + i))
    assert cache.load_files("k1") == {"annotations.json": b"{}", "meshes/m.ply": b"\0"}  # used: now the newest
    cache.store_files("k3", {"annotations.json": b"[]"})
    assert sorted(p.stem for p in (tmp_path / "collections").glob("*.npz")) == ["k1", "k3"]
    assert cache.store_files("k4", {"../evil": b"x"}) is None and cache.load_files("k4") is None
