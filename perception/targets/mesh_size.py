"""How many triangles a mesh file will make, read before the mesh is built.

A file's size does not bound the memory its mesh takes: an OBJ face line ``f 1 2 3`` is 8 bytes,
a binary PLY face 13, and a glTF node may instance one mesh a thousand times, while trimesh holds
about a kilobyte per triangle while loading. :func:`triangle_bound` reads only what it must (the
text's face lines, a PLY header and its face section, a glTF's JSON) to bound the triangle count,
so that :func:`perception.targets.loading.load_target` refuses a file that would eat the machine's
memory before trimesh reads it.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np

#: Bytes read at a time from a text mesh (the arrays made from one chunk take ~10x its size).
_CHUNK = 8 * 2**20
_SPACE = np.zeros(256, dtype=bool)
_SPACE[[9, 11, 12, 13, 32]] = True  # tab, vertical tab, form feed, CR, space (newline apart)


def triangle_bound(path: Path) -> int | None:
    """An upper bound on the triangles ``trimesh.load(path, force="mesh")`` makes, or None for a
    format whose size bounds it already (STL: at least 50 bytes a triangle) or that is not read
    here (trimesh then reads it under the file-size limit alone).

    - OBJ: each face line of k vertices makes k - 2 triangles (a polygon is fanned);
    - PLY: binary, from the header's counts and types and the size of the face section; ASCII,
      from the face section's lines; OFF likewise;
    - GLB / glTF: each primitive's index (or position) count, times the number of times the
      scene graph reaches the nodes that hold its mesh (instancing).

    Raises:
        ValueError: a glTF whose node hierarchy has a cycle (it never ends).
    """
    suffix = path.suffix.lower()
    if suffix == ".obj":
        return _obj_triangles(path)
    if suffix == ".ply":
        return _ply_triangles(path)
    if suffix == ".off":
        return _off_triangles(path)
    if suffix in (".glb", ".gltf"):
        return _gltf_triangles(path)
    return None


# ---------------------------------------------------------------------------------------------
# Text: triangles of a line from its whitespace-separated tokens
# ---------------------------------------------------------------------------------------------
def _chunks(path: Path, start: int) -> Iterator[bytes]:
    """The file from byte ``start`` in chunks that end at a newline (the last one at the end)."""
    tail = b""
    with path.open("rb") as f:
        f.seek(start)
        while True:
            block = f.read(_CHUNK)
            if not block:
                if tail:
                    yield tail + b"\n"
                return
            block = tail + block
            cut = block.rfind(b"\n") + 1
            tail = block[cut:]
            if cut:
                yield block[:cut]


def _line_tokens(chunk: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each line of a chunk that ends in a newline: its number of tokens, the first byte of
    its first token and the byte after that one (a blank line: 0 tokens, 0 and a newline)."""
    a = np.frombuffer(chunk, dtype=np.uint8)
    newline = a == 10
    sep = _SPACE[a] | newline
    starts = np.flatnonzero(~sep & np.concatenate(([True], sep[:-1])))
    line_of_byte = np.cumsum(newline) - newline
    n_lines = int(newline.sum())
    line = line_of_byte[starts]
    count = np.bincount(line, minlength=n_lines)
    first = np.ones(len(starts), dtype=bool)
    first[1:] = line[1:] != line[:-1]
    head = np.zeros(n_lines, dtype=np.uint8)
    after = np.full(n_lines, 10, dtype=np.uint8)
    pos = starts[first]
    head[line[first]] = a[pos]
    nxt = np.minimum(pos + 1, len(a) - 1)
    after[line[first]] = a[nxt]
    return count, head, after


def _obj_triangles(path: Path) -> int:
    total = 0
    for chunk in _chunks(path, 0):
        count, head, after = _line_tokens(chunk)
        face = (head == ord("f")) & (_SPACE[after] | (after == 10))
        total += int(np.maximum(count[face] - 3, 0).sum())  # the keyword and 2 vertices: 0
    return total


# ---------------------------------------------------------------------------------------------
# PLY
# ---------------------------------------------------------------------------------------------
_PLY_TYPES = {
    "char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2,
    "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4,
    "double": 8, "float64": 8,
}


def _ply_triangles(path: Path) -> int | None:
    """None when the header cannot be read (trimesh then says what is wrong with the file)."""
    with path.open("rb") as f:
        header = f.read(64 * 1024)
    end = header.find(b"end_header")
    if not header.startswith(b"ply") or end < 0:
        return None
    body = header.find(b"\n", end) + 1
    lines = header[:end].decode("ascii", "replace").splitlines()
    fmt = ""
    elements: list[tuple[str, int, list[list[str]]]] = []
    for ln in lines:
        w = ln.split()
        if len(w) >= 2 and w[0] == "format":
            fmt = w[1]
        elif len(w) >= 3 and w[0] == "element":
            try:
                elements.append((w[1], int(w[2]), []))
            except ValueError:
                return None
        elif w and w[0] == "property" and elements:
            elements[-1][2].append(w[1:])
    names = [e[0] for e in elements]
    if "face" not in names:
        return 0
    k = names.index("face")
    n_faces, props = elements[k][1], elements[k][2]
    if fmt == "ascii":
        return _section_triangles(path, body, sum(e[1] for e in elements[:k]), n_faces)
    # Binary: bytes before the face section from the fixed-size elements before it (a list
    # property before the faces makes that unknown: count the faces' section from the end).
    skip = 0
    for _, n, ps in elements[:k]:
        if any(p and p[0] == "list" for p in ps):
            skip = 0
            break
        skip += n * sum(_PLY_TYPES.get(p[0], 1) for p in ps if p)
    section = max(path.stat().st_size - body - skip, 0)
    lists = [p for p in props if p and p[0] == "list" and len(p) >= 3]
    if not lists:
        return n_faces
    fixed = sum(_PLY_TYPES.get(p[0], 1) for p in props if p and p[0] != "list")
    count_bytes = sum(_PLY_TYPES.get(p[1], 1) for p in lists)
    index_bytes = min(_PLY_TYPES.get(p[2], 1) for p in lists)
    # Every face spends `fixed + count_bytes` bytes, and its k indices `index_bytes` each.
    indices = max(section - n_faces * (fixed + count_bytes), 0) // index_bytes
    return max(int(indices) - 2 * n_faces, n_faces)


def _section_triangles(path: Path, body: int, before: int, n_faces: int) -> int:
    """Face lines of an ASCII PLY or OFF, from byte ``body`` after ``before`` element lines:
    each ``k i1 .. ik`` (then other properties, which only raise the bound)."""
    total, skipped, seen = 0, 0, 0
    for chunk in _chunks(path, body):
        count, _, _ = _line_tokens(chunk)
        count = count[count > 0]  # blank lines are no element
        take = count[max(before - skipped, 0):]
        skipped += len(count) - len(take)
        take = take[: max(n_faces - seen, 0)]
        seen += len(take)
        total += int(np.maximum(take - 3, 0).sum())  # a face's other properties only add
        if seen >= n_faces:
            break
    return total


def _off_triangles(path: Path) -> int | None:
    """OFF: ``OFF``, then ``nv nf ne``, the vertex lines and the face lines (``#`` comments
    before the counts are skipped; None when the counts cannot be read)."""
    with path.open("rb") as f:
        head = f.read(64 * 1024)
    pos, words = 0, []
    while len(words) < 3 and pos < len(head):
        end = head.find(b"\n", pos)
        if end < 0:
            return None
        line = head[pos:end].split(b"#")[0].split()
        pos = end + 1
        if line and line[0].upper().endswith(b"OFF") and not words:
            line = line[1:]
        words += line
    try:
        nv, nf = int(words[0]), int(words[1])
    except (IndexError, ValueError):
        return None
    return _section_triangles(path, pos, nv, nf)


# ---------------------------------------------------------------------------------------------
# glTF
# ---------------------------------------------------------------------------------------------
def _gltf_json(path: Path) -> dict | None:
    with path.open("rb") as f:
        head = f.read(20)
        if head[:4] == b"glTF":
            if len(head) < 20:
                return None
            length, kind = struct.unpack("<II", head[12:20])
            if kind != 0x4E4F534A:  # "JSON"
                return None
            text = f.read(min(length, path.stat().st_size))
        else:
            f.seek(0)
            text = f.read()
    try:
        doc = json.loads(text)
    except (ValueError, UnicodeError):
        return None
    return doc if isinstance(doc, dict) else None


def _gltf_triangles(path: Path) -> int | None:
    doc = _gltf_json(path)
    if doc is None:
        return None
    try:
        return _gltf_count(path, doc)
    except (TypeError, KeyError, IndexError, AttributeError):
        return None  # malformed: trimesh says what is wrong


def _gltf_count(path: Path, doc: dict) -> int:
    accessors = doc.get("accessors", [])
    meshes = doc.get("meshes", [])
    nodes = doc.get("nodes", [])
    per_mesh = []
    for mesh in meshes:
        tris = 0
        for prim in mesh.get("primitives", []):
            ref = prim.get("indices", prim.get("attributes", {}).get("POSITION"))
            n = int(accessors[ref]["count"]) if ref is not None else 0
            mode = int(prim.get("mode", 4))
            tris += n // 3 if mode == 4 else max(n - 2, 0) if mode in (5, 6) else 0
        per_mesh.append(tris)
    if not nodes:
        return sum(per_mesh)
    # Times each node is reached from the scenes' roots (a node may be listed as a child more
    # than once in a hostile file, so count paths, with a cycle refused).
    roots = [r for s in doc.get("scenes", []) for r in s.get("nodes", [])]
    if not roots:
        children = {c for nd in nodes for c in nd.get("children", [])}
        roots = [i for i in range(len(nodes)) if i not in children]
    state = [0] * len(nodes)  # 0 new, 1 on the stack, 2 done
    below = [0] * len(nodes)  # triangles in a node's subtree, counted once per reach of it

    def subtree(i: int) -> int:
        stack = [(i, 0)]
        while stack:
            node, k = stack.pop()
            kids = nodes[node].get("children", [])
            if k == 0:
                if state[node] == 2:  # a root reached earlier as another root's child
                    continue
                state[node] = 1
            if k < len(kids):
                stack.append((node, k + 1))
                child = int(kids[k])
                if state[child] == 1:
                    raise ValueError(
                        f"target mesh file {path}: its glTF node hierarchy has a cycle through"
                        f" node {child}; expected a tree"
                    )
                if state[child] == 0:
                    stack.append((child, 0))
                continue
            m = nodes[node].get("mesh")
            own = per_mesh[int(m)] if m is not None else 0
            below[node] = min(own + sum(below[int(c)] for c in kids), 1 << 62)
            state[node] = 2
        return below[i]

    total = 0
    for r in roots:
        total = min(total + subtree(int(r)), 1 << 62)
    return total
