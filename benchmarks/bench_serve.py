"""Load test of `geoloc serve`: latency percentiles, throughput and errors under concurrent clients.

Starts `python -m geoloc.cli serve ckpt=... gallery=...` (uvicorn, one process) on a free loopback port, waits for
/health, sends a few warm-up requests, then --clients threads each POST --requests street panoramas to /localize
(bounded by --max-seconds as well). Prints p50 / p99 / mean latency, the throughput and the error count (anything but
200; it must be 0), first for one client alone (the latency of one request) and then for all clients at once.

--limits measures instead the costliest requests the limits allow (geoloc.apps.query.QueryLimits): a panorama of
max_pixels searched at max_headings candidate headings, a limited-fov photo whose canvas is max_canvas_side columns
and max_pixels pixels, and requests just past each limit (which must get 413 at once), one at a time against an idle
server; for each it prints the latency and the server's peak memory (VmHWM) above its level after the warm-up. The
cases at topk=max_topk are the refiner's costliest (every top-k tile is refined): with a refiner checkpoint and its
gallery (--ckpt, --gallery: e.g. experiment=refine_vigor and its unknown-heading variant) each line says how many
tiles were refined.

Without --ckpt / --gallery it builds them in --work (default $GEOLOC_CACHE/bench_serve, reused by later runs): the
default recipe (`python train.py`) on a small synthetic render, stopped after one training step (the weights are
as good as untrained; speed does not depend on them), and its gallery (`python evaluate.py gallery.save=DIR`).
The queries are that render's street panoramas, sent as the JPEG files they are.

    nice -n 5 python benchmarks/bench_serve.py                      # 4 clients x 10 requests
    nice -n 5 python benchmarks/bench_serve.py --heading 0          # north-aligned: no heading search
    nice -n 5 python benchmarks/bench_serve.py --limits             # the costliest requests the limits allow
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


def start_server(ckpt: Path, gallery: Path, port: int, env: dict, log: Path,
                 extra: tuple[str, ...] = ()) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "geoloc.cli", "serve", f"ckpt={ckpt}", f"gallery={gallery}", f"port={port}",
           "device=cpu", *extra]
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


def memory_mb(pid: int, key: str) -> float:
    """VmRSS (resident memory now) or VmHWM (its peak since the last reset_peak) of a process, in MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(f"{key}:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no {key} in /proc/{pid}/status: --limits needs Linux")


def reset_peak(pid: int) -> None:
    """Start VmHWM again from the current resident memory (Linux: 5 > /proc/PID/clear_refs)."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")


def resized_jpeg(source: bytes, width: int, height: int) -> bytes:
    """A street image scaled to width x height, as a JPEG (quality 90)."""
    import cv2

    image = cv2.imdecode(np.frombuffer(source, np.uint8), cv2.IMREAD_COLOR)
    return cv2.imencode(".jpg", cv2.resize(image, (width, height), interpolation=cv2.INTER_LINEAR),
                        [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()


def limit_requests(url: str, server: subprocess.Popen, source: bytes) -> None:
    """The costliest requests the default limits allow, and requests just past them, one at a time: latency, status
    and the server's peak memory above its level after the warm-up."""
    from geoloc.apps.query import QueryLimits

    limits = QueryLimits()
    side, pixels = limits.max_canvas_side, limits.max_pixels
    pano_w = int((2 * pixels) ** 0.5)  # a 2:1 panorama of max_pixels
    photo_h = pixels // side  # a fov=90 photo whose canvas is max_canvas_side x photo_h <= max_pixels
    most = str(limits.max_topk)
    cases = [  # (what, width, height, form fields, expected status)
        ("VIGOR-size panorama 2048x1024, heading searched", 2048, 1024, {}, 200),
        (f"VIGOR-size panorama 2048x1024, heading given, topk={most}", 2048, 1024, {"heading": "0", "topk": most},
         200),
        (f"VIGOR-size panorama 2048x1024, heading searched, topk={most}", 2048, 1024, {"topk": most}, 200),
        (f"max_pixels panorama {pano_w}x{pano_w // 2}, heading searched, topk={most}", pano_w, pano_w // 2,
         {"topk": most}, 200),
        (f"max_pixels panorama {pano_w}x{pano_w // 2}, heading given", pano_w, pano_w // 2, {"heading": "0"}, 200),
        (f"max_pixels panorama {pano_w}x{pano_w // 2}, heading searched", pano_w, pano_w // 2, {}, 200),
        (f"fov=90 photo {side // 4}x{photo_h}: canvas {side}x{photo_h}, heading searched", side // 4, photo_h,
         {"fov": "90"}, 200),
        ("fov=0.1 on a 512x256 panorama (1,843,200 canvas columns)", 512, 256, {"fov": "0.1"}, 413),
        ("65,500x2 strip", 65_500, 2, {}, 413),
        (f"fov=90 photo {side // 4 + 8}x{photo_h}: past max_canvas_side", side // 4 + 8, photo_h, {"fov": "90"}, 413),
    ]
    print(f"server resident memory after the warm-up (model, gallery, first requests): "
          f"{memory_mb(server.pid, 'VmRSS'):.0f} MB", flush=True)
    with httpx.Client(base_url=url, timeout=600) as http:
        for what, width, height, fields, expect in cases:
            data = resized_jpeg(source, width, height)
            before = memory_mb(server.pid, "VmRSS")
            reset_peak(server.pid)
            start = time.perf_counter()
            answer = http.post("/localize", files={"image": ("q.jpg", data, "image/jpeg")}, data=fields)
            seconds = time.perf_counter() - start
            note = f": {answer.json()['detail'][:100]}..." if answer.status_code != 200 else ""
            refined = answer.status_code == 200 and sum("refined_position" in hit for hit in answer.json()["topk"])
            note = f", {refined} tiles refined" if refined else note
            print(f"{what} ({len(data) / 1e6:.1f} MB JPEG): {answer.status_code} in {seconds:.2f} s, peak "
                  f"{memory_mb(server.pid, 'VmHWM') - before:+.0f} MB over the {before:.0f} MB before{note}",
                  flush=True)
            if answer.status_code != expect:
                print(f"  UNEXPECTED: wanted {expect}", flush=True)


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
    parser.add_argument("--limits", action="store_true", help="the costliest requests the limits allow (docstring)")
    parser.add_argument("--heading-steps", type=int, help="the server's heading_steps (default the checkpoint's)")
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
    extra = () if args.heading_steps is None else (f"heading_steps={args.heading_steps}",)
    server = start_server(ckpt, gallery, port, env, args.work / "server.log", extra)
    url = f"http://127.0.0.1:{port}"
    try:
        if args.limits:
            load(url, images, 1, 3, args.max_seconds, {})  # warm-up
            limit_requests(url, server, images[0][1])
            return
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
