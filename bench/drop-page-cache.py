#!/usr/bin/env python3
"""Drops the OS page cache of a scene's stores (posix_fadvise DONTNEED, as bench-store does),
so that each mode of a benchmark starts its first frame cold, not from pages an earlier mode
read.

    python3 bench/drop-page-cache.py SCENE.toml

Stores are the [[volume]] and [[horizon]] `store` paths and every .strata file in the
[synthetic] `dir`, relative to the scene file's folder.
"""
import os
import sys

try:
    import tomllib
except ImportError:  # Python before 3.11: say so, and let the benchmark go on warm
    tomllib = None


def main() -> None:
    scene = sys.argv[1]
    if tomllib is None:
        print("warning: no tomllib (Python < 3.11): page cache not dropped", file=sys.stderr)
        return
    base = os.path.dirname(os.path.abspath(scene))
    with open(scene, "rb") as f:
        s = tomllib.load(f)
    paths = [l["store"] for k in ("volume", "horizon") for l in s.get(k, []) if "store" in l]
    syn = s.get("synthetic", {}).get("dir")
    if syn:
        d = os.path.join(base, syn)
        if os.path.isdir(d):
            paths += [os.path.join(d, n) for n in os.listdir(d) if n.endswith(".strata")]
    dropped = 0
    for p in sorted({os.path.realpath(os.path.join(base, p)) for p in paths}):
        if not os.path.isfile(p):
            continue
        fd = os.open(p, os.O_RDONLY)
        try:
            os.fsync(fd)
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
            dropped += 1
        finally:
            os.close(fd)
    print(f"dropped the page cache of {dropped} store(s)", file=sys.stderr)


if __name__ == "__main__":
    main()
