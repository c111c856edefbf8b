"""The 3D view's data of one object: its mesh decimated, quantised and written as a registration script.

A mesh is decimated to at most ``max_faces`` faces (quadric decimation, ``fast-simplification``) and written as
``carviReport.mesh(key, data)`` with int16-quantised positions (:func:`encode_mesh`), so the page can load it
from disk (``file://``) by a script tag. :func:`write_mesh_script` does it all for one mesh file; it imports
numpy, the mesh reader and the decimation only (no torch), so that a run's writer processes, which have them
loaded already, make the scripts while the run's own process draws the rest of the report.

Example:
    >>> v = np.array([[0, 0, 0], [2, 0, 0], [0, 4, 0]], float)
    >>> d = encode_mesh(v, np.array([[0, 1, 2]]))
    >>> d["half"], d["centre"], d["index_bits"]
    (2.0, [1.0, 2.0, 0.0], 16)
    >>> np.allclose(decode_positions(d), v, atol=2.0 / 32767)
    True
"""
from __future__ import annotations

import base64
import json
from pathlib import Path

import numpy as np

from ..io.outputs import write_within

__all__ = ["encode_mesh", "decode_positions", "decimated", "write_mesh_script"]


def _b64(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a).tobytes()).decode("ascii")


def encode_mesh(vertices: np.ndarray, faces: np.ndarray) -> dict:
    """``vertices (V, 3)`` float, ``faces (F, 3)`` int -> a JSON-able dict: little-endian int16
    positions quantised in the bounding box (``centre``, ``half``: the largest half extent), base64,
    and uint16 (``V < 65536``) or uint32 indices, base64."""
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre = (lo + hi) / 2
    half = float(max((hi - lo).max() / 2, 1e-9))
    q = np.clip(np.round((v - centre) / half * 32767), -32767, 32767).astype("<i2")
    bits = 16 if len(v) < 65536 else 32
    idx = np.asarray(faces).astype("<u2" if bits == 16 else "<u4")
    return {"centre": [float(c) for c in centre], "half": half, "positions": _b64(q), "index": _b64(idx),
            "index_bits": bits}


def decode_positions(d: dict) -> np.ndarray:
    """``(V, 3)`` float64 vertices of :func:`encode_mesh`'s output (what the page computes)."""
    q = np.frombuffer(base64.b64decode(d["positions"]), dtype="<i2").reshape(-1, 3)
    return q / 32767.0 * d["half"] + np.asarray(d["centre"])


def decimated(path: Path, max_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Float32 vertices and int32 faces of the mesh file ``path`` (:func:`~carvi_torch.mesh.read_mesh_arrays`),
    simplified to about ``max_faces`` faces where it has more."""
    from ..mesh import read_mesh_arrays

    v, f = read_mesh_arrays(path)
    v, f = v.astype(np.float32), f.astype(np.int32)
    if len(f) > max_faces:
        import fast_simplification

        v, f = fast_simplification.simplify(v, f, target_count=max_faces)
    return v, f


def write_mesh_script(src: str, out: str, rel: str, key: str, max_faces: int) -> tuple[int | None, str | None]:
    """Decimate the mesh file ``src`` (:func:`decimated`) and write it as the registration script ``out/rel``
    (:func:`~carvi_torch.io.outputs.write_within`) under ``key``. Returns ``(faces, None)``, or ``(None, reason)``
    for a mesh that cannot be read (nothing written). Plain arguments and results: it runs in worker processes too.
    """
    try:
        v, f = decimated(Path(src), max_faces)
    except Exception as e:  # noqa: BLE001 - a damaged mesh: the card says so
        return None, f"mesh unreadable ({type(e).__name__}: {str(e)[:80]}): no 3D view"
    data = encode_mesh(v, f)
    text = f"carviReport.mesh({json.dumps(key)},{json.dumps(data, separators=(',', ':'))});\n"
    write_within(Path(out), rel, text.encode(), sync=False)
    return int(len(f)), None
