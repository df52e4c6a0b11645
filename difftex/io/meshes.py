"""Meshes (OBJ parser / trimesh) in difftex's conventions.

Conventions (DESIGN.md section 2): textures are ``[1, C, H, W]`` floats in
``[0, 1]``; uv ``(0, 0)`` is the top-left corner of the texture with ``v``
running down the rows, so mesh loaders convert the files' v-up coordinate
with ``v = 1 - v_file``.

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
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..geometry.mesh import Mesh
from .files import PathLike, check_file

__all__ = ["MESH_EXTENSIONS", "load_mesh"]

MESH_EXTENSIONS = (".obj", ".glb", ".gltf", ".ply")


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
                if tag == "v":
                    v.append([float(x) for x in parts[1:4]])
                elif tag == "vt":
                    # vt u [v [w]]: a missing v means 0 per the OBJ spec.
                    u = float(parts[1])
                    vv = float(parts[2]) if len(parts) > 2 else 0.0
                    vt.append([u, vv])
                elif tag == "vn":
                    vn.append([float(x) for x in parts[1:4]])
                elif tag == "f":
                    corners = []
                    for c in parts[1:]:
                        idx = c.split("/")
                        iv = int(idx[0])
                        it = int(idx[1]) if len(idx) > 1 and idx[1] else 0
                        inn = int(idx[2]) if len(idx) > 2 and idx[2] else 0
                        # OBJ is 1-based; negative indices count back from the
                        # elements read so far.  0 marks "absent".
                        iv = iv - 1 if iv > 0 else len(v) + iv
                        it = (it - 1 if it > 0 else len(vt) + it) if it else -1
                        inn = (inn - 1 if inn > 0 else len(vn) + inn) if inn else -1
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
        device, dtype: of the float fields; index fields are int64.

    Returns:
        A :class:`Mesh` with uv in DESIGN.md's convention, ``v = 1 - v_file``.

    Nothing here is differentiable (it is file input).  Raises
    FileNotFoundError for a missing file, ValueError naming the path for an
    unsupported extension, a file without faces or without uv, an
    unparsable line or an out-of-range index.
    """
    path = check_file(path, "mesh", MESH_EXTENSIONS)
    if path.suffix.lower() == ".obj":
        arrays = _load_obj(path)
    else:
        arrays = _load_trimesh(path)
    pos, faces, uv, uv_faces, normals, normal_faces = arrays

    def f(a):
        return None if a is None else torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=device)

    def i(a):
        return None if a is None else torch.as_tensor(np.ascontiguousarray(a), dtype=torch.int64, device=device)

    return Mesh(f(pos), i(faces), f(uv), i(uv_faces), f(normals), i(normal_faces))

