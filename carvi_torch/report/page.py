"""``index.html``: the run's header, one panel per class, the card grid's controls and legend.

Every value taken from the run is HTML-escaped; the cards themselves are drawn by
``static/report.js`` from ``cards.js``.

Example:
    >>> "<b>" in class_panel_html({"objects": 2, "failures": [{"annotation_id": 1, "reason": "<b>"}]},
    ...                           "car", "car", None, None)
    False
"""
from __future__ import annotations

from html import escape
from urllib.parse import quote

from ..io.layout import objects_text, other_settings_text, settings_record
from .cards import legend

__all__ = ["class_panel_html", "index_html", "MAX_REASONS"]

#: Skipped objects listed per class panel (all of them are in ``summary.json``).
MAX_REASONS = 200


def _counts(entry: dict) -> str:
    keys = [("objects", "objects"), ("reconstructed", "reconstructed"), ("resumed", "resumed"),
            ("skipped", "skipped")]
    head = "".join(f"<th>{label}</th>" for _, label in keys) + "<th>warnings</th><th>seconds</th>"
    secs = sum(v for v in (entry.get("seconds") or {}).values() if isinstance(v, (int, float)))
    cells = "".join(f"<td>{escape(str(entry.get(k, '-')))}</td>" for k, _ in keys)
    cells += f"<td>{len(entry.get('warnings') or [])}</td><td>{secs:.1f}</td>"
    return f"<table class=counts><tr>{head}</tr><tr>{cells}</tr></table>"


def _reasons(entry: dict) -> str:
    failures = [f for f in entry.get("failures") or [] if isinstance(f, dict)]
    warnings = [str(w) for w in entry.get("warnings") or []]
    parts = []
    if failures:
        items = "".join(f"<li>{escape(str(f.get('annotation_id', 'class')))}"
                        f"{' (' + escape(str(f['source'])) + ')' if f.get('source') else ''}: "
                        f"{escape(str(f.get('stage', '')))}: {escape(str(f.get('reason', '')))}</li>"
                        for f in failures[:MAX_REASONS])
        more = f"<li>and {len(failures) - MAX_REASONS} more (summary.json)</li>" if len(failures) > MAX_REASONS else ""
        parts.append(f"<details open><summary>skipped ({len(failures)})</summary><ul class=reasons>{items}{more}</ul>"
                     "</details>")
    if warnings:
        parts.append(f"<details><summary>warnings ({len(warnings)})</summary><ul class=reasons>"
                     + "".join(f"<li>{escape(w)}</li>" for w in warnings) + "</ul></details>")
    return "".join(parts)


def class_panel_html(entry: dict, key: str, name: str, chart: str | None, problem: str | None) -> str:
    """One class's panel: counts, SfM residual, the figure (``chart``: its relative path), reasons."""
    sfm = entry.get("sfm") if isinstance(entry.get("sfm"), dict) else {}
    med = sfm.get("median_residual_px")
    line = f"SfM median keypoint residual {med:.2f} px" if isinstance(med, (int, float)) else "no SfM residual"
    frame = entry.get("frame") if isinstance(entry.get("frame"), dict) else {}
    if frame.get("kind"):
        line += f"; canonical frame: {escape(str(frame['kind']))}"
    img = (f"<img class=chart src='{escape(chart)}' alt='viewpoints, residuals and silhouette agreement of "
           f"{escape(name)}'>") if chart else ""
    warn = f"<p class=reason>{escape(problem)}</p>" if problem else ""
    link = escape(quote(key, safe=""))  # URL-encoded: a key with '%' or '&' still names its class in the hash
    return (f"<details class=class-panel open data-class='{escape(key)}'><summary>{escape(name)}"
            f"{' (folder ' + escape(key) + ')' if key != name else ''}</summary>{warn}{_counts(entry)}"
            f"<p>{line} (objects: <a href='#class={link}&amp;page=1'>cards</a>)</p>{img}{_reasons(entry)}"
            "</details>")


def _legend_html() -> str:
    items = []
    for kind, colour, text in legend():
        if kind == "cross":
            items.append(f"<span><span class='cross' style='color:{colour}'>&times;</span> {escape(text)}</span>")
        else:
            items.append(f"<span><span class='sw {kind}' style='background:{colour}'></span>{escape(text)}</span>")
    return "<div class=legend id=legend-template>" + "".join(items) + "</div>"


def _header(summary: dict, title: str, n_cards: int, sort_by: str, objects: tuple | None = None) -> str:
    classes = summary.get("classes") or {}
    total = sum(int(c.get("objects", 0) or 0) for c in classes.values() if isinstance(c, dict))
    done = sum(int(c.get("reconstructed", 0) or 0) for c in classes.values() if isinstance(c, dict))
    secs = summary.get("total_seconds")
    problems = summary.get("input_problems") or []
    line = (f"{len(classes)} classes, {total} objects, {done} reconstructed, {n_cards} cards "
            f"(worst first by {escape(sort_by)})")
    if isinstance(secs, (int, float)):
        line += f"; run took {secs:.1f} s on {escape(str(summary.get('device', '?')))}"
    extra = f"<p>input problems reported at load: {len(problems)} (summary.json)</p>" if problems else ""
    return f"<header><h1>{escape(title)}</h1><p>{line}</p>{extra}{_other_settings(summary, objects)}</header>"


def _other_settings(summary: dict, objects: tuple | None = None) -> str:
    """A line saying the run's objects were made with other settings than its ``config.yaml``'s (``summary.json``'s
    ``resumed_from_other_settings``; ``objects``: how many by their voxels files,
    :func:`~carvi_torch.io.layout.objects_made_otherwise`), or nothing.

    Example:
        >>> _other_settings({"resumed_from_other_settings": {"carve.resolution": [16, 24]}})[:92]
        '<p class=warn>objects made with other settings than config.yaml: carve.resolution 16 then 24'
    """
    made = settings_record(summary.get("resumed_from_other_settings"))
    if not made:
        return ""
    values, counted = other_settings_text(made), objects_text(objects) if objects else ""
    text = (f"objects made with other settings than config.yaml: {values} (oldest first, then this run's"
            + (f"; {counted}" if counted else "") + "; reconstruct with overwrite=true makes them alike)")
    return f"<p class=warn>{escape(text)}</p>"


def index_html(summary: dict, title: str, panels: list[str], classes: list[tuple[str, str]], n_cards: int,
               sort_by: str, objects: tuple | None = None) -> str:
    """The whole page; ``classes``: ``(key, name)`` of every class for the filter; ``objects``: how many objects
    were made with other settings by their voxels files (:func:`~carvi_torch.io.layout.objects_made_otherwise`),
    where the run records any."""
    options = "<option value=all>all classes</option>" + "".join(
        f"<option value='{escape(k)}'>{escape(n)}</option>" for k, n in classes)
    return f"""<!doctype html>
<html lang=en><head><meta charset=utf-8><title>{escape(title)}</title>
<meta name=viewport content='width=device-width, initial-scale=1'>
<link rel=stylesheet href='assets/report.css'></head>
<body data-ready=0>
{_header(summary, title, n_cards, sort_by, objects)}
<h2>Classes</h2>
<div class=class-grid>{''.join(panels)}</div>
<h2 id=objects>Objects</h2>
<div class=controls><label>class <select id=class-filter>{options}</select></label>
<button id=prev type=button>previous</button><button id=next type=button>next</button>
<span id=page-info></span></div>
{_legend_html()}
<div id=cards></div>
<script src='assets/three.min.js'></script>
<script src='assets/OrbitControls.js'></script>
<script src='assets/report.js'></script>
<script src='cards.js'></script>
<script>carviReport.start();</script>
</body></html>
"""
