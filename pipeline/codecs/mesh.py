"""Triangle mesh files: PLY (binary little-endian out; binary or ASCII in) and Wavefront OBJ + MTL.

Meshes are ``vertices (V, 3)`` metres (world frame) and ``faces (F, 3)`` int, counter-clockwise seen from
outside. UVs follow the OBJ convention (u right, v up, [0, 1]). Files are written under a temporary name
and renamed, so readers never see half a file; non-finite values are refused.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from pipeline.errors import InputError

__all__ = ["write_ply", "read_ply", "write_obj", "read_obj"]

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _atomic_write(path: Path, data: bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)
    return path


def _check(vertices, faces, normals=None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces must be (F, 3), got {f.shape}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"faces index vertices outside [0, {len(v)})")
    if not np.all(np.isfinite(v)):
        raise ValueError("refusing to write non-finite vertices (NaN or Inf)")
    n = None
    if normals is not None:
        n = np.asarray(normals)
        if n.shape != v.shape:
            raise ValueError(f"normals must be (V, 3) like vertices {v.shape}, got {n.shape}")
        if not np.all(np.isfinite(n)):
            raise ValueError("refusing to write non-finite normals (NaN or Inf)")
    return v, f, n


# ---------------------------------------------------------------------------------------------- PLY
def write_ply(path: str | Path, vertices: np.ndarray, faces: np.ndarray,
              normals: np.ndarray | None = None, comment: str = "UltraStage mesh, world frame, metres") -> Path:
    """Binary little-endian PLY: float32 ``x y z`` (+ ``nx ny nz``), faces as ``uchar`` count + ``int`` ids."""
    path = Path(path)
    v, f, n = _check(vertices, faces, normals)
    props = ["x", "y", "z"] + (["nx", "ny", "nz"] if n is not None else [])
    header = ["ply", "format binary_little_endian 1.0", f"comment {comment}", f"element vertex {len(v)}"]
    header += [f"property float {p}" for p in props]
    header += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    vert = np.concatenate([v, n], axis=1) if n is not None else v
    face_rec = np.empty(len(f), dtype=[("n", "u1"), ("ids", "<i4", (3,))])
    face_rec["n"] = 3
    face_rec["ids"] = f
    data = ("\n".join(header) + "\n").encode("ascii") + np.ascontiguousarray(vert, "<f4").tobytes() \
        + face_rec.tobytes()
    return _atomic_write(path, data)


def _ply_header(path: Path, raw: bytes) -> tuple[str, list, int]:
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise InputError(path, "not a PLY file (no 'ply' magic or no end_header)")
    newline = raw.find(b"\n", end)
    body_start = newline + 1 if newline >= 0 else len(raw)
    fmt = None
    elements: list = []  # [name, count, [(prop, dtype) | (prop, count_dtype, item_dtype)]]
    for line in raw[:end].decode("ascii", errors="replace").splitlines()[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append([words[1], int(words[2]), []])
        elif words[0] == "property" and elements:
            try:
                if words[1] == "list":
                    elements[-1][2].append((words[4], _PLY_TYPES[words[2]], _PLY_TYPES[words[3]]))
                else:
                    elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
            except (KeyError, IndexError) as error:
                raise InputError(path, f"bad PLY property line {line!r}") from error
    if fmt not in ("binary_little_endian", "binary_big_endian", "ascii"):
        raise InputError(path, f"unsupported PLY format {fmt!r}")
    return fmt, elements, body_start


def read_ply(path: str | Path, with_normals: bool = False):
    """Read a triangle (or polygon, fan-triangulated) PLY.

    Returns:
        vertices (V, 3) float32, faces (F, 3) int32; with ``with_normals`` also normals (V, 3) float32 or
        None when the file has none.

    Raises:
        InputError: not a PLY, unsupported layout, truncated, out-of-range indices or non-finite values.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as error:
        raise InputError(path, f"cannot read: {error}") from error
    fmt, elements, offset = _ply_header(path, raw)
    endian = ">" if fmt == "binary_big_endian" else "<"
    tokens = raw[offset:].split() if fmt == "ascii" else None
    pos = 0  # token cursor (ascii)
    vertices = normals = None
    faces = np.zeros((0, 3), np.int64)
    for name, count, props in elements:
        scalar = all(len(p) == 2 for p in props)
        if fmt == "ascii":
            if scalar:
                width = len(props)
                table = np.array(tokens[pos:pos + count * width], dtype=np.float64)
                if table.size != count * width:
                    raise InputError(path, f"truncated PLY element {name!r}")
                table = table.reshape(count, width)
                pos += count * width
                columns = {p[0]: table[:, i] for i, p in enumerate(props)}
            else:
                columns, lists = {}, []
                for _ in range(count):
                    row = []
                    for p in props:
                        if len(p) == 3:
                            k = int(tokens[pos])
                            row.append([int(t) for t in tokens[pos + 1:pos + 1 + k]])
                            pos += 1 + k
                        else:
                            pos += 1
                    lists.append(row)
                columns = {p[0]: [r[i] for r in lists] for i, p in enumerate(props) if len(p) == 3}
        elif scalar:
            dtype = np.dtype([(p[0], endian + p[1]) for p in props])
            nbytes = dtype.itemsize * count
            if offset + nbytes > len(raw):
                raise InputError(path, f"truncated PLY element {name!r}")
            table = np.frombuffer(raw, dtype=dtype, count=count, offset=offset)
            offset += nbytes
            columns = {p[0]: table[p[0]] for p in props}
        else:
            columns, offset = _read_binary_lists(path, raw, offset, count, props, endian)
        if name == "vertex":
            if not all(k in columns for k in "xyz"):
                raise InputError(path, "PLY vertex element lacks x, y or z")
            vertices = np.stack([columns["x"], columns["y"], columns["z"]], axis=1).astype(np.float32)
            if all(k in columns for k in ("nx", "ny", "nz")):
                normals = np.stack([columns["nx"], columns["ny"], columns["nz"]], axis=1).astype(np.float32)
        elif name == "face":
            key = "vertex_indices" if "vertex_indices" in columns else "vertex_index"
            if key not in columns:
                raise InputError(path, "PLY face element has no vertex_indices list")
            faces = columns[key] if isinstance(columns[key], np.ndarray) else _fan(columns[key])
    if vertices is None:
        raise InputError(path, "PLY has no vertex element")
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise InputError(path, "PLY faces index vertices that do not exist")
    if not np.all(np.isfinite(vertices)):
        raise InputError(path, "PLY vertices hold NaN or Inf")
    faces = faces.astype(np.int32).reshape(-1, 3)
    return (vertices, faces, normals) if with_normals else (vertices, faces)


def _fan(polygons: list) -> np.ndarray:
    tris = [(p[0], p[i], p[i + 1]) for p in polygons for i in range(1, len(p) - 1)]
    return np.asarray(tris, np.int64).reshape(-1, 3)


def _read_binary_lists(path, raw, offset, count, props, endian):
    """Binary element with list properties: fast path for all-triangle faces, else a row loop."""
    if len(props) == 1 and len(props[0]) == 3 and count:
        name, count_t, item_t = props[0]
        tri = np.dtype([("n", endian + count_t), ("ids", endian + item_t, (3,))])
        if offset + tri.itemsize * count <= len(raw):
            table = np.frombuffer(raw, dtype=tri, count=count, offset=offset)
            if np.all(table["n"] == 3):
                return {name: table["ids"].astype(np.int64)}, offset + tri.itemsize * count
    lists: dict[str, list] = {p[0]: [] for p in props if len(p) == 3}
    try:
        for _ in range(count):
            for p in props:
                if len(p) == 3:
                    k = int(np.frombuffer(raw, endian + p[1], 1, offset)[0])
                    offset += np.dtype(p[1]).itemsize
                    lists[p[0]].append(np.frombuffer(raw, endian + p[2], k, offset).tolist())
                    offset += k * np.dtype(p[2]).itemsize
                else:
                    offset += np.dtype(p[1]).itemsize
    except ValueError as error:
        raise InputError(path, "truncated PLY list element") from error
    return lists, offset


# ---------------------------------------------------------------------------------------------- OBJ
def _fmt_rows(prefix: str, array: np.ndarray, fmt: str) -> str:
    if not len(array):
        return ""
    line = prefix + " " + " ".join([fmt] * array.shape[1])
    return "\n".join(line % tuple(row) for row in array.tolist()) + "\n"


def write_obj(path: str | Path, vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray | None = None,
              uv_faces: np.ndarray | None = None, normals: np.ndarray | None = None,
              material: dict | None = None) -> Path:
    """Wavefront OBJ, with a ``.mtl`` beside it when ``material`` is given.

    Args:
        vertices: (V, 3) metres; faces: (F, 3) int (0-based here, 1-based in the file).
        uvs: (U, 2) texture coordinates (OBJ convention, v up); uv_faces: (F, 3) int into ``uvs``
            (defaults to ``faces`` when ``uvs`` has one row per vertex).
        normals: (V, 3) per-vertex normals, indexed like the vertices.
        material: MTL statements of one material, e.g. ``{"name": "skin", "map_Kd": "albedo.png",
            "norm": "normal.exr"}``; texture file names are written as given (relative to the OBJ's
            folder). ``name`` defaults to ``"material0"``, ``Kd`` to ``1 1 1``. The MTL file is
            ``<stem>.mtl``.
    """
    path = Path(path)
    v, f, n = _check(vertices, faces, normals)
    lines = ["# UltraStage mesh, world frame, metres; uv: OBJ convention (v up)\n"]
    if material is not None:
        lines.append(f"mtllib {path.stem}.mtl\n")
    lines.append(_fmt_rows("v", v.astype(np.float64), "%.7g"))
    vt = None
    if uvs is not None:
        vt = np.asarray(uvs, np.float64)
        if vt.ndim != 2 or vt.shape[1] != 2 or not np.all(np.isfinite(vt)):
            raise ValueError(f"uvs must be a finite (U, 2) array, got {vt.shape}")
        uf = np.asarray(uv_faces if uv_faces is not None else f)
        if uv_faces is None and len(vt) != len(v):
            raise ValueError("uv_faces is needed when uvs are not one per vertex")
        if uf.shape != f.shape or (uf.size and (uf.min() < 0 or uf.max() >= len(vt))):
            raise ValueError(f"uv_faces must be (F, 3) indices into uvs, got {uf.shape}")
        lines.append(_fmt_rows("vt", vt, "%.7g"))
    if n is not None:
        lines.append(_fmt_rows("vn", n.astype(np.float64), "%.6g"))
    if material is not None:
        lines.append(f"usemtl {material.get('name', 'material0')}\n")
    f1 = f.astype(np.int64) + 1
    if vt is not None and n is not None:
        corners, corner_fmt = np.stack([f1, uf + 1, f1], axis=2), "%d/%d/%d"
    elif vt is not None:
        corners, corner_fmt = np.stack([f1, uf + 1], axis=2), "%d/%d"
    elif n is not None:
        corners, corner_fmt = np.stack([f1, f1], axis=2), "%d//%d"
    else:
        corners, corner_fmt = f1[:, :, None], "%d"
    if len(f):
        line = "f " + " ".join([corner_fmt] * 3)
        lines.append("\n".join(line % tuple(row) for row in corners.reshape(len(f), -1).tolist()) + "\n")
    if material is not None:
        mtl = dict(material)
        name = mtl.pop("name", "material0")
        mtl.setdefault("Kd", "1 1 1")
        body = [f"newmtl {name}"]
        for key, value in mtl.items():
            if isinstance(value, (list, tuple, np.ndarray)):
                value = " ".join(f"{x:g}" for x in value)
            body.append(f"{key} {value}")
        _atomic_write(path.with_suffix(".mtl"), ("\n".join(body) + "\n").encode("utf-8"))
    return _atomic_write(path, "".join(lines).encode("utf-8"))


def read_obj(path: str | Path) -> dict:
    """Read an OBJ written by :func:`write_obj` (triangles or polygons, fan-triangulated).

    Returns:
        ``vertices`` (V, 3) float32, ``faces`` (F, 3) int32, ``uvs`` (U, 2) float32 or None,
        ``uv_faces`` (F, 3) int32 or None, ``normals`` (N, 3) float32 or None, ``normal_faces`` or None,
        ``mtllib`` (str or None), ``material`` (dict of the MTL's statements, or None).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise InputError(path, f"cannot read: {error}") from error
    fast = _read_obj_columns(text)
    if fast is not None:
        v, vt, vn, fv, ft, fn, mtllib = fast
    else:
        v, vt, vn, fv, ft, fn, mtllib = _read_obj_lines(path, text)

    def _faces(rows, n_items):
        if len(rows) == 0:
            return None
        arr = np.asarray(rows, np.int64)
        arr = np.where(arr < 0, arr + n_items, arr - 1)  # OBJ: 1-based, negatives count from the end
        if arr.min() < 0 or arr.max() >= n_items:
            raise InputError(path, "face indices out of range")
        return arr.astype(np.int32)

    vertices = np.asarray(v, np.float32).reshape(-1, 3)
    material = None
    if mtllib is not None and (path.parent / mtllib).exists():
        material = {}
        for line in (path.parent / mtllib).read_text(encoding="utf-8").splitlines():
            m = re.match(r"\s*(\S+)\s+(.*\S)\s*$", line)
            if m and not m.group(1).startswith("#"):
                key = "name" if m.group(1) == "newmtl" else m.group(1)
                material[key] = m.group(2)
    faces = _faces(fv, len(vertices))
    return {"vertices": vertices, "faces": faces if faces is not None else np.zeros((0, 3), np.int32),
            "uvs": np.asarray(vt, np.float32).reshape(-1, 2) if len(vt) else None, "uv_faces": _faces(ft, len(vt)),
            "normals": np.asarray(vn, np.float32).reshape(-1, 3) if len(vn) else None,
            "normal_faces": _faces(fn, len(vn)), "mtllib": mtllib, "material": material}


def _read_obj_columns(text: str) -> tuple | None:
    """The statements of an OBJ laid out as :func:`write_obj` writes it (``v``/``vt``/``vn`` lines of 3/2/3
    numbers, triangles ``f a/b/c`` with the same corner layout on every face, comments, ``mtllib`` and
    ``usemtl``), parsed a statement kind at a time with numpy: ``(v, vt, vn, fv, ft, fn, mtllib)`` as
    :func:`_read_obj_lines` gives them. None when the file holds anything else (that reader then parses it
    line by line and names the line it cannot read)."""
    lines = text.splitlines()
    groups: dict[str, list[str]] = {"v": [], "vt": [], "vn": [], "f": []}
    mtllib = None
    for line in lines:
        head, _, rest = line.partition(" ")
        group = groups.get(head)
        if group is not None:
            group.append(rest)
        elif head == "mtllib":
            mtllib = " ".join(rest.split())
        elif not (head == "" and not line.strip()) and not head.startswith("#") and head != "usemtl":
            return None

    def numbers(rows: list[str], width: int, dtype) -> np.ndarray | None:
        if not rows:
            return np.zeros((0, width), dtype)
        if not all(len(row.split()) == width for row in rows):
            return None
        flat = " ".join(rows).split()
        try:
            return np.array(flat, dtype=np.float64 if dtype is float else np.int64).reshape(-1, width)
        except ValueError:
            return None

    columns = [numbers(groups[kind], width, float) for kind, width in (("v", 3), ("vt", 2), ("vn", 3))]
    if any(c is None for c in columns) or not groups["f"]:
        return None if any(c is None for c in columns) else (*columns, [], [], [], mtllib)
    parts = groups["f"][0].split()[0].split("/")
    present = [bool(p) for p in parts]  # the corner layout: v, v/t, v/t/n or v//n
    if len(parts) > 3 or not present[0] or (len(parts) == 2 and not present[1]):
        return None
    field = [r"-?\d+" if p else "" for p in present]
    corner = "/".join(field)
    triangle = re.compile(f"{corner} {corner} {corner}")
    if not all(triangle.fullmatch(row.strip()) for row in groups["f"]):
        return None
    width = sum(present)
    corners = numbers([row.replace("/", " ") for row in groups["f"]], 3 * width, int)
    if corners is None:
        return None
    corners = corners.reshape(-1, 3, width)
    column = {kind: i for i, kind in enumerate(k for k, p in zip("vtn", present) if p)}
    fv = corners[:, :, 0]
    ft = corners[:, :, column["t"]] if "t" in column else []
    fn = corners[:, :, column["n"]] if "n" in column else []
    return (*columns, fv, ft, fn, mtllib)


def _read_obj_lines(path: Path, text: str) -> tuple:
    """Any OBJ's vertex, uv and normal rows and its faces (fan-triangulated), a line at a time."""
    v, vt, vn, fv, ft, fn = [], [], [], [], [], []
    mtllib = None
    for number, line in enumerate(text.splitlines(), 1):
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        try:
            if words[0] == "v":
                v.append([float(x) for x in words[1:4]])
            elif words[0] == "vt":
                vt.append([float(x) for x in words[1:3]])
            elif words[0] == "vn":
                vn.append([float(x) for x in words[1:4]])
            elif words[0] == "mtllib":
                mtllib = " ".join(words[1:])
            elif words[0] == "f":
                corners = [w.split("/") for w in words[1:]]
                for i in range(1, len(corners) - 1):
                    tri = (corners[0], corners[i], corners[i + 1])
                    fv.append([int(c[0]) for c in tri])
                    if len(corners[0]) > 1 and corners[0][1]:
                        ft.append([int(c[1]) for c in tri])
                    if len(corners[0]) > 2 and corners[0][2]:
                        fn.append([int(c[2]) for c in tri])
        except (ValueError, IndexError) as error:
            raise InputError(path, f"line {number}: cannot parse {line!r}") from error
    return v, vt, vn, fv, ft, fn, mtllib
