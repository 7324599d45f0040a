"""Load test of `geoloc serve`: latency percentiles, throughput and errors under concurrent clients.

Starts `python -m geoloc.cli serve ckpt=... gallery=...` (uvicorn, one process) on a free loopback port, waits for
/health, sends a few warm-up requests, then --clients threads each POST --requests street panoramas to /localize
(bounded by --max-seconds as well). Prints p50 / p99 / mean latency, the throughput and the error count (anything but
200; it must be 0), first for one client alone (the latency of one request) and then for all clients at once.

Without --ckpt / --gallery it builds them in --work (default $GEOLOC_CACHE/bench_serve, reused by later runs): the
default recipe (`python train.py`) on a small synthetic render, stopped after one training step (the weights are
as good as untrained; speed does not depend on them), and its gallery (`python evaluate.py gallery.save=DIR`).
The queries are that render's street panoramas, sent as the JPEG files they are.

    nice -n 5 python benchmarks/bench_serve.py                      # 4 clients x 10 requests
    nice -n 5 python benchmarks/bench_serve.py --heading 0          # north-aligned: no heading search
    python benchmarks/bench_serve.py --clients 8 --requests 25 --ckpt RUN/best.pt --gallery DIR --images 'DIR/*.jpg'
"""
from __future__ import annotations

import argparse
import glob
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]


def run(cmd: list[str], env: dict) -> None:
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, cwd=REPO, env=env, check=True)


def build(work: Path, val_size: int, env: dict) -> tuple[Path, Path]:
    """A one-step checkpoint of the default recipe and its saved gallery of `val_size` references."""
    ckpt, gallery = work / "run" / "best.pt", work / "gallery"
    if not ckpt.is_file():
        run([sys.executable, "train.py", "trainer.max_epochs=1", "trainer.limit_train_batches=1", "figures=false",
             "trainer.progress=false", "dataset.train_size=32", f"dataset.val_size={val_size}",
             f"hydra.run.dir={work / 'run'}"], env)
    if not (gallery / "gallery.json").is_file():
        run([sys.executable, "evaluate.py", f"ckpt={ckpt}", f"gallery.save={gallery}", "progress=false",
             "device=cpu", f"hydra.run.dir={work / 'evaluate'}"], env)
    return ckpt, gallery


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def start_server(ckpt: Path, gallery: Path, port: int, env: dict, log: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "geoloc.cli", "serve", f"ckpt={ckpt}", f"gallery={gallery}", f"port={port}",
           "device=cpu"]
    print("+", " ".join(cmd), f"> {log}", flush=True)
    server = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:
        if server.poll() is not None:
            raise RuntimeError(f"the server exited with code {server.returncode}; see {log}")
        try:
            health = httpx.get(f"http://127.0.0.1:{port}/health", timeout=2)
            print("health:", health.json(), flush=True)
            return server
        except httpx.TransportError:
            time.sleep(0.5)
    server.terminate()
    raise RuntimeError(f"the server did not answer /health within 180 s; see {log}")


def load(url: str, images: list[tuple[str, bytes]], clients: int, requests: int, max_seconds: float,
         fields: dict) -> dict:
    """`clients` threads x `requests` POSTs each (fewer once max_seconds have passed); latencies in ms."""
    latencies, errors, lock = [], [], threading.Lock()
    stop_at = time.monotonic() + max_seconds

    def client(c: int) -> None:
        with httpx.Client(base_url=url, timeout=120) as http:
            for r in range(requests):
                if time.monotonic() > stop_at:
                    return
                name, data = images[(c * requests + r) % len(images)]
                start = time.perf_counter()
                try:
                    answer = http.post("/localize", files={"image": (name, data, "image/jpeg")}, data=fields)
                    ok = answer.status_code == 200
                    problem = None if ok else f"{answer.status_code}: {answer.text[:200]}"
                except httpx.HTTPError as err:
                    problem = f"{type(err).__name__}: {err}"
                with lock:
                    latencies.append(1000 * (time.perf_counter() - start))
                    if problem:
                        errors.append(problem)

    threads = [threading.Thread(target=client, args=(c,)) for c in range(clients)]
    start = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - start
    ms = np.array(latencies)
    return {"clients": clients, "requests": len(ms), "errors": len(errors), "first_error": errors[:1],
            "p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)),
            "mean_ms": float(ms.mean()), "throughput_rps": len(ms) / wall, "wall_s": wall}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--requests", type=int, default=10, help="per client")
    parser.add_argument("--max-seconds", type=float, default=120, help="stop sending after this long (per phase)")
    parser.add_argument("--ckpt", type=Path)
    parser.add_argument("--gallery", type=Path)
    parser.add_argument("--images", help="glob of query images (default: the built render's panoramas)")
    parser.add_argument("--work", type=Path,
                        default=Path(os.environ.get("GEOLOC_CACHE", Path.home() / ".cache/geoloc")) / "bench_serve")
    parser.add_argument("--gallery-size", type=int, default=200, help="references, when building")
    parser.add_argument("--heading", type=float, help="send this heading (no search over the 36 candidates)")
    args = parser.parse_args()
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
           "GEOLOC_CACHE": str(args.work / "cache")}
    args.work.mkdir(parents=True, exist_ok=True)
    ckpt, gallery = (args.ckpt, args.gallery) if args.ckpt else build(args.work, args.gallery_size, env)
    pattern = args.images or str(args.work / "cache" / "**" / "panos" / "*.jpg")
    files = sorted(glob.glob(pattern, recursive=True))[:50]
    if not files:
        sys.exit(f"no query images match {pattern}: give --images 'DIR/*.jpg'")
    images = [(Path(f).name, Path(f).read_bytes()) for f in files]
    print(f"{len(images)} query images, e.g. {files[0]} ({len(images[0][1]):,} bytes)")
    port = free_port()
    server = start_server(ckpt, gallery, port, env, args.work / "server.log")
    url = f"http://127.0.0.1:{port}"
    try:
        fields = {} if args.heading is None else {"heading": str(args.heading)}
        load(url, images, 1, 3, args.max_seconds, fields)  # warm-up: first-call allocations, grid caches
        for clients, requests in ((1, args.requests), (args.clients, args.requests)):
            figures = load(url, images, clients, requests, args.max_seconds, fields)
            print(f"{clients} client(s) x {requests} requests: {figures['requests']} done, errors "
                  f"{figures['errors']} {figures['first_error'] or ''}\n  latency p50 {figures['p50_ms']:.0f} ms, "
                  f"p99 {figures['p99_ms']:.0f} ms, mean {figures['mean_ms']:.0f} ms; throughput "
                  f"{figures['throughput_rps']:.2f} requests/s over {figures['wall_s']:.1f} s", flush=True)
    finally:
        server.terminate()
        server.wait(30)


if __name__ == "__main__":
    main()
