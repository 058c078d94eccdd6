"""Load test of ``wamplan wam serve`` on this machine only (127.0.0.1): N concurrent clients, bounded.

The server runs as the real command (``python -m wamplan.cli wam serve``) in a subprocess with a shared secret
(passed in ``$WAMPLAN_ACT_SECRET``, never on the command line). Each client thread sends its share of the
requests through ``CosmosPolicyClient``; request i carries observation ``i % --distinct`` (224-px views and
proprio drawn from seed i % distinct), and its answer (actions and every predicted view) must equal what the
same checkpoint, called directly in this process, answers for that observation: a mixed-up reply shows as a
mismatch. Also checked: a request without the secret gets HTTP 401. Prints requests/s, p50/p99 latency,
errors and mismatches. The server answers one query at a time (a WAM holds one model), so throughput is
the model's; the figures on a shared 2-core machine swing with the other jobs.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/act_server.py --clients 8 --requests 200 --time-cap-s 60
"""

from __future__ import annotations

import argparse
import os
import secrets
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import requests

from wamplan.envs.contract import CAMERAS, Observation
from wamplan.serving import HEALTH_ROUTE, SECRET_ENV
from wamplan.wam import load_wam, protocol
from wamplan.wam.cosmos_client import CosmosClientConfig, CosmosPolicyClient

HOST = "127.0.0.1"  # never anything else


def free_port() -> int:
    with socket.socket() as s:
        s.bind((HOST, 0))
        return s.getsockname()[1]


def make_obs(i: int, size: int) -> Observation:
    rng = np.random.default_rng(i)
    return Observation(step=0, proprio=rng.uniform(-1, 1, 10).astype(np.float32),
                       images={c: rng.integers(0, 256, (size, size, 3), dtype=np.uint8) for c in CAMERAS})


def wait_healthy(url: str, proc: subprocess.Popen, timeout_s: float = 120.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the server exited with code {proc.returncode} before answering /health")
        try:
            return requests.get(url, timeout=2).json()
        except requests.exceptions.ConnectionError:
            time.sleep(0.2)
    raise RuntimeError(f"the server did not answer {url} within {timeout_s:g} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ckpt", default="checkpoints/mini/tinywam", help="WAM checkpoint to serve")
    ap.add_argument("--clients", type=int, default=8, help="concurrent client threads")
    ap.add_argument("--requests", type=int, default=200, help="requests in all (split between the clients)")
    ap.add_argument("--time-cap-s", type=float, default=60.0, help="clients stop sending after this many seconds")
    ap.add_argument("--distinct", type=int, default=16, help="distinct observations (answers checked per one)")
    ap.add_argument("--image-size", type=int, default=224, help="side of the sent views, pixels")
    args = ap.parse_args()

    direct = load_wam(args.ckpt)
    obs = [make_obs(i, args.image_size) for i in range(args.distinct)]
    want = [direct.predict(o, direct.default_instruction) for o in obs]
    assert len({w.actions.tobytes() for w in want}) == args.distinct, "the distinct observations must differ"

    port, secret = free_port(), secrets.token_urlsafe(16)
    env = {**os.environ, SECRET_ENV: secret, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    src = str(Path(__file__).resolve().parents[1] / "src")
    env["PYTHONPATH"] = src + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.Popen([sys.executable, "-m", "wamplan.cli", "wam", "serve", "--ckpt", args.ckpt,
                             "--host", HOST, "--port", str(port), "--log-level", "warning"], env=env)
    base = f"http://{HOST}:{port}"
    try:
        health = wait_healthy(base + HEALTH_ROUTE, proc)
        print(f"server: {health}")
        refused = requests.post(base + protocol.ROUTE, data=b"{}", headers=protocol.JSON_HEADERS, timeout=10)
        print(f"without the secret: HTTP {refused.status_code} {refused.text}")

        latencies: list[float] = []
        errors: list[str] = []
        mismatches: list[int] = []
        lock = threading.Lock()
        counter = iter(range(args.requests))
        start = threading.Barrier(args.clients + 1)
        cap = {"deadline": 0.0}

        def client_loop() -> None:
            c = CosmosPolicyClient(CosmosClientConfig(url=base + protocol.ROUTE, retries=0, timeout_s=120),
                                   secret=secret)
            start.wait()
            while time.monotonic() < cap["deadline"]:
                with lock:
                    i = next(counter, None)
                if i is None:
                    break
                k = i % args.distinct
                t0 = time.perf_counter()
                try:
                    out = c.predict(obs[k], direct.default_instruction)
                except Exception as e:  # counted and reported
                    with lock:
                        errors.append(f"request {i}: {e}")
                    continue
                dt = time.perf_counter() - t0
                same = np.array_equal(out.actions, want[k].actions) and all(
                    np.array_equal(out.images[cam], want[k].images[cam]) for cam in want[k].images)
                with lock:
                    latencies.append(dt)
                    if not same:
                        mismatches.append(i)
            c.close()

        threads = [threading.Thread(target=client_loop) for _ in range(args.clients)]
        for t in threads:
            t.start()
        cap["deadline"] = time.monotonic() + args.time_cap_s
        t_start = time.perf_counter()
        start.wait()
        for t in threads:
            t.join()
        wall = time.perf_counter() - t_start
    finally:
        proc.terminate()
        proc.wait(30)

    done = len(latencies)
    lat = np.array(latencies) * 1e3  # (done,) ms
    print(f"clients {args.clients}, requests {done + len(errors)} of {args.requests} (time cap "
          f"{args.time_cap_s:g} s), {args.image_size}-px views, wall {wall:.1f} s")
    if done:
        print(f"throughput {done / wall:.2f} requests/s; latency p50 {np.percentile(lat, 50):.0f} ms, "
              f"p99 {np.percentile(lat, 99):.0f} ms, max {lat.max():.0f} ms")
    print(f"errors {len(errors)}; replies not matching their request {len(mismatches)}")
    for e in errors[:5]:
        print("  ", e)


if __name__ == "__main__":
    main()
