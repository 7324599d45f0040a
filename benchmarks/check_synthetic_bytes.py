"""Byte identity of the synthetic renderer between two checkouts: every file of every layout, sha256 by sha256.

    python benchmarks/check_synthetic_bytes.py --ref /path/to/other/checkout [--n 6] [--cases cvusa:small ...]

Each case (layout:preset) is generated with n train + n val samples (vigor: panoramas per city; u1652: buildings;
dynamic: places) by this checkout and by the one at --ref, each in a subprocess with its own PYTHONPATH, and all
files are compared. Exits 1 on any difference. A speed-up of the renderer must pass this against the code before it.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]
CASES = ["cvusa:tiny", "cvusa:small", "cvusa:cvusa", "cvact:tiny", "cvact:small", "dynamic:dynamic_tiny",
         "dynamic:dynamic_small", "vigor:vigor_tiny", "vigor:vigor_small", "u1652:u1652_tiny", "u1652:u1652_small"]
CHILD = """
import json, sys, hashlib
from pathlib import Path
import cv2
cv2.setNumThreads(1)
from geoloc.synthetic import generate
layout, preset, n, out = sys.argv[1], sys.argv[2], int(sys.argv[3]), Path(sys.argv[4])
root = generate(layout, out, train=n, val=n, preset=preset, progress=False)
print(json.dumps({p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
                  for p in sorted(root.rglob("*")) if p.is_file()}))
"""


def digests(code: Path, layout: str, preset: str, n: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, PYTHONPATH=str(code), OMP_NUM_THREADS="1")
        out = subprocess.run([sys.executable, "-c", CHILD, layout, preset, str(n), str(Path(tmp) / "d")],
                             env=env, cwd=tmp, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--ref", type=Path, required=True, help="the other checkout (e.g. a worktree of main)")
    p.add_argument("--n", type=int, default=6)
    p.add_argument("--cases", nargs="*", default=CASES, help="layout:preset pairs")
    p.add_argument("--ref-cache", type=Path, help="a JSON file keeping --ref's digests between runs (the reference "
                   "code does not change while one works on the other)")
    a = p.parse_args()
    cache = json.loads(a.ref_cache.read_text()) if a.ref_cache and a.ref_cache.exists() else {}
    bad = total = 0
    for case in a.cases:
        layout, preset = case.split(":")
        key = f"{case}:{a.n}"
        if key not in cache:
            cache[key] = digests(a.ref.resolve(), layout, preset, a.n)
            if a.ref_cache:
                a.ref_cache.write_text(json.dumps(cache))
        mine, ref = digests(HERE, layout, preset, a.n), cache[key]
        diff = sorted(f for f in set(mine) | set(ref) if mine.get(f) != ref.get(f))
        total += len(ref)
        bad += len(diff)
        print(f"{case:24s} {len(ref):5d} files  {'identical' if not diff else f'{len(diff)} DIFFER: {diff[:5]}'}",
              flush=True)
    print(f"{total} files compared, {bad} differ")
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
