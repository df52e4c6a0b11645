"""Meshes (own OBJ parser / trimesh for GLB, glTF, PLY) in difftex's conventions.

Conventions (DESIGN.md section 2): textures are ``[1, C, H, W]`` floats (in
``[0, 1]`` from 8- / 16-bit files); uv ``(0, 0)`` is the top-left corner of
the texture with ``v`` running down the rows, so mesh loaders convert the
files' v-up coordinate with ``v = 1 - v_file``.

Why OBJ has its own parser: an OBJ face corner indexes positions (``v``),
texture coordinates (``vt``) and normals (``vn``) independently.  trimesh
cannot keep that: with ``process=False, maintain_order=True`` it keeps the
2930 spot positions but only one uv per position (the seam corners get a
wrong uv), and without ``maintain_order`` it splits seam vertices (spot
becomes 3225 vertices) and reorders them.  The small parser below keeps the
file's positions, uv list and per-corner indices exactly.  The other formats
(GLB / glTF / PLY) store one uv per vertex in the file itself, so trimesh's
vertex list is already the exact content of the file and ``uv_faces`` equals
``faces`` there.

What is rejected rather than loaded (ValueError naming the file): NaN or
infinite coordinates (OBJ: with the line, other formats: with the field),
since one of them poisons every sum a rasterizer or sampler forms; face
indices out of range, or past int64 (numpy would raise a bare
OverflowError).  Float fields take a floating ``dtype`` only (TypeError
otherwise: an integer dtype would truncate uv).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..geometry.mesh import Mesh
from .files import PathLike, check_file

__all__ = ["MESH_EXTENSIONS", "load_mesh"]

MESH_EXTENSIONS = (".obj", ".glb", ".gltf", ".ply")

_INDEX_LIMIT = 2 ** 62  # far past any real element count, safely inside int64 after the 1-based shift


def _coords(parts: list[str], n: int) -> list[float]:
    """The first ``n`` numbers of a v / vt / vn line; ValueError for NaN / inf (they would poison every sum)."""
    xs = [float(x) for x in parts[:n]]
    if not all(math.isfinite(x) for x in xs):
        raise ValueError(f"non-finite coordinate {xs}; expected finite numbers")
    return xs


def _index(text: str, count: int) -> int:
    """A 1-based (or negative, relative) OBJ index as 0-based; ValueError past int64."""
    i = int(text)
    # An index this large can never be in range; int64 conversion would raise a bare OverflowError.
    if not -_INDEX_LIMIT < i < _INDEX_LIMIT:
        raise ValueError(f"index {text} out of the int64 range")
    return i - 1 if i > 0 else count + i


def _parse_obj(path: Path):
    """Positions, uv, normals and per-corner index triples of an OBJ file.

    Polygons are fan-triangulated (as trimesh does); negative (relative)
    indices are resolved; ``l``/``p``/groups/materials are ignored.
    """
    v, vt, vn = [], [], []
    fv, ft, fn = [], [], []
    # utf-8-sig: a byte-order mark would otherwise hide the first line's tag.
    with open(path, "r", encoding="utf-8-sig", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            parts = line.split()
            if not parts:
                continue
            tag = parts[0]
            try:
                if tag in ("v", "vn") and len(parts) < 4:
                    raise ValueError(f"'{tag}' needs 3 coordinates")
                if tag == "vt" and len(parts) < 2:
                    raise ValueError("'vt' needs at least a u coordinate")
                if tag == "v":
                    v.append(_coords(parts[1:], 3))
                elif tag == "vt":
                    # vt u [v [w]]: a missing v means 0 per the OBJ spec.
                    vt.append((_coords(parts[1:], 2) + [0.0])[:2])
                elif tag == "vn":
                    vn.append(_coords(parts[1:], 3))
                elif tag == "f":
                    corners = []
                    for c in parts[1:]:
                        idx = c.split("/")
                        # OBJ is 1-based; negative indices count back from the
                        # elements read so far.  -1 marks "absent".
                        iv = _index(idx[0], len(v))
                        it = _index(idx[1], len(vt)) if len(idx) > 1 and idx[1] else -1
                        inn = _index(idx[2], len(vn)) if len(idx) > 2 and idx[2] else -1
                        corners.append((iv, it, inn))
                    if len(corners) < 3:
                        raise ValueError("a face needs at least 3 corners")
                    for k in range(1, len(corners) - 1):
                        tri = (corners[0], corners[k], corners[k + 1])
                        fv.append([c[0] for c in tri])
                        ft.append([c[1] for c in tri])
                        fn.append([c[2] for c in tri])
            except (ValueError, IndexError) as exc:
                raise ValueError(f"{str(path)!r} line {lineno}: cannot parse {line.strip()!r} ({exc})") from None
    return (np.asarray(v, dtype=np.float64).reshape(-1, 3),
            np.asarray(vt, dtype=np.float64).reshape(-1, 2),
            np.asarray(vn, dtype=np.float64).reshape(-1, 3),
            np.asarray(fv, dtype=np.int64).reshape(-1, 3),
            np.asarray(ft, dtype=np.int64).reshape(-1, 3),
            np.asarray(fn, dtype=np.int64).reshape(-1, 3))


def _check_indices(path: Path, name: str, idx: np.ndarray, count: int) -> None:
    if idx.size and (idx.min() < 0 or idx.max() >= count):
        raise ValueError(
            f"{str(path)!r}: {name} index out of range [0, {count}) "
            f"(found {idx.min()}..{idx.max()})"
        )


def _load_obj(path: Path):
    v, vt, vn, fv, ft, fn = _parse_obj(path)
    if fv.shape[0] == 0:
        raise ValueError(f"{str(path)!r} has no faces; expected a triangle mesh with uv")
    if vt.shape[0] == 0 or (ft < 0).all():
        raise ValueError(
            f"{str(path)!r} has no texture coordinates; expected 'vt' lines and faces "
            "written as f v/vt or f v/vt/vn"
        )
    if (ft < 0).any():
        bad = int(np.nonzero((ft < 0).any(axis=1))[0][0])
        raise ValueError(
            f"{str(path)!r}: triangle {bad} has a corner without a texture coordinate; "
            "expected every face corner to carry a vt index"
        )
    _check_indices(path, "position", fv, v.shape[0])
    _check_indices(path, "texture coordinate", ft, vt.shape[0])
    normals = normal_faces = None
    if vn.shape[0] and (fn >= 0).all():
        _check_indices(path, "normal", fn, vn.shape[0])
        normals, normal_faces = vn, fn
    uv = vt.copy()
    uv[:, 1] = 1.0 - uv[:, 1]
    return v, fv, uv, ft, normals, normal_faces


def _load_trimesh(path: Path):
    import trimesh

    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises a zoo of types for broken files
        raise ValueError(f"trimesh could not read {str(path)!r}: {exc}") from exc
    parts = []  # (positions, faces, uv or None, normals or None)
    if isinstance(loaded, trimesh.Scene):
        for node in loaded.graph.nodes_geometry:
            transform, name = loaded.graph[node]
            g = loaded.geometry[name]
            if not isinstance(g, trimesh.Trimesh):
                continue
            pos = trimesh.transform_points(np.asarray(g.vertices), transform)
            nrm = None
            if "vertex_normals" in g._cache:  # loaded from the file, not computed
                nrm = np.asarray(g.vertex_normals) @ np.linalg.inv(transform[:3, :3])
                nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
            parts.append((pos, np.asarray(g.faces), getattr(g.visual, "uv", None), nrm))
    elif isinstance(loaded, trimesh.Trimesh):
        nrm = np.asarray(loaded.vertex_normals) if "vertex_normals" in loaded._cache else None
        parts.append((np.asarray(loaded.vertices), np.asarray(loaded.faces),
                      getattr(loaded.visual, "uv", None), nrm))
    if not parts or sum(p[1].shape[0] for p in parts) == 0:
        raise ValueError(f"{str(path)!r} has no triangles; expected a triangle mesh with uv")
    if any(p[2] is None or len(p[2]) != len(p[0]) for p in parts):
        raise ValueError(f"{str(path)!r} has no texture coordinates; expected a mesh with uv")
    offset, faces = 0, []
    for p in parts:
        faces.append(np.asarray(p[1], dtype=np.int64) + offset)
        offset += p[0].shape[0]
    positions = np.concatenate([p[0] for p in parts])
    faces = np.concatenate(faces)
    uv = np.concatenate([np.asarray(p[2], dtype=np.float64) for p in parts])
    # trimesh stores uv v-up for every format (it flips glTF's v on load).
    uv[:, 1] = 1.0 - uv[:, 1]
    normals = normal_faces = None
    if all(p[3] is not None for p in parts):
        normals = np.concatenate([p[3] for p in parts])
        normal_faces = faces
    return positions, faces, uv, faces, normals, normal_faces


def load_mesh(path: PathLike, *, device=None, dtype: torch.dtype = torch.float32) -> Mesh:
    """Load a textured triangle mesh with exact face-varying uv.

    Args:
        path: ``.obj`` (own parser, keeps the file's v / vt / vn lists and
            per-corner indices; polygons are fan-triangulated) or ``.glb`` /
            ``.gltf`` / ``.ply`` through trimesh (one uv per vertex, scene
            transforms applied, several meshes concatenated).
        device: of every field.
        dtype: of the float fields (positions, uv, normals), a floating
            ``torch.dtype``; index fields are int64.

    Returns:
        A :class:`Mesh` with uv in DESIGN.md's convention, ``v = 1 - v_file``.

    Nothing here is differentiable (it is file input).  Raises TypeError
    naming ``path`` when it is no str / PathLike and naming ``dtype`` when
    it is not a floating torch.dtype (an integer dtype would truncate uv);
    FileNotFoundError for a missing file; ValueError naming the path for an
    unsupported extension, a file without faces or without uv, an
    unparsable line, a NaN / infinite coordinate (OBJ: with its line; other
    formats: with the field), an index past int64 or out of range.
    """
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(f"dtype must be a floating torch.dtype such as torch.float32 (it is the dtype of "
                        f"positions, uv and normals), got {dtype!r}")
    path = check_file(path, "mesh", MESH_EXTENSIONS)
    if path.suffix.lower() == ".obj":
        arrays = _load_obj(path)
    else:
        arrays = _load_trimesh(path)
    pos, faces, uv, uv_faces, normals, normal_faces = arrays
    for name, a in (("positions", pos), ("uv", uv), ("normals", normals)):
        # The OBJ parser already names the line; this catches the binary formats.
        if a is not None and not np.isfinite(a).all():
            raise ValueError(f"{str(path)!r}: {name} has NaN or infinite values; expected finite coordinates")

    def f(a):
        return None if a is None else torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=device)

    def i(a):
        return None if a is None else torch.as_tensor(np.ascontiguousarray(a), dtype=torch.int64, device=device)

    return Mesh(f(pos), i(faces), f(uv), i(uv_faces), f(normals), i(normal_faces))
