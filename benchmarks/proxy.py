"""Latency of the planning proxy (``wamplan serve``) on this machine, over loopback, side by side in one run:

* ``direct``: the WAM served by ``wamplan wam serve``'s app, one request a chunk;
* ``proxy open loop``: the same request through the proxy when the world model lacks its history (forward,
  decode, re-encode: the proxy's own overhead);
* ``proxy planned``: through the proxy with the frames seen during the chunk sent (the world model plans);
* ``openpi open loop`` / ``openpi planned``: the same two through the proxy's WebSocket front end, sent by
  openpi's own client (``openpi_client.WebsocketClientPolicy``, msgpack instead of json_numpy).

Every request carries three views of --size px and a 10-D proprio; the upstream is the shipped TinyWAM
(in the proxy's process) and the world model the shipped wm_augmented. Prints p50 / mean per kind in ms.

    OMP_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python benchmarks/proxy.py --chunks 8 --size 224
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings
from pathlib import Path

import json_numpy
import numpy as np
import requests
from openpi_client.websocket_client_policy import WebsocketClientPolicy

from wamplan.proxy.app import create_proxy_app
from wamplan.planning.policy_config import PlannedPolicyConfig
from wamplan.proxy.build import build_proxy
from wamplan.proxy.config import ProxyConfig
from wamplan.serving.runner import BackgroundServer
from wamplan.wam import load_wam, protocol
from wamplan.wam.server import create_app

CKPTS = Path(__file__).resolve().parents[1] / "checkpoints" / "mini"
FIELDS = {"primary_image": "front", "left_wrist_image": "side", "right_wrist_image": "wrist"}


def frame(rng: np.random.Generator, size: int) -> dict:
    return {**{f: rng.integers(0, 256, (size, size, 3), dtype=np.uint8) for f in FIELDS},
            "proprio": rng.uniform(-0.5, 0.5, 10).astype(np.float32)}


def timed(url: str, payload: dict) -> tuple[float, dict]:
    t0 = time.perf_counter()
    r = requests.post(url, data=json_numpy.dumps(payload), headers=protocol.JSON_HEADERS, timeout=120)
    dt = time.perf_counter() - t0
    r.raise_for_status()
    return dt, json_numpy.loads(r.text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--chunks", type=int, default=8, help="chunks per kind (default 8)")
    ap.add_argument("--size", type=int, default=224, help="side of the views sent (default 224)")
    args = ap.parse_args()
    warnings.simplefilter("ignore", UserWarning)  # TinyWAM's note on the view size; it does not change timings
    rng = np.random.default_rng(0)
    times: dict[str, list[float]] = {"direct": [], "proxy open loop": [], "proxy planned": [],
                                     "openpi open loop": [], "openpi planned": []}
    # the seen history: a request without its in-chunk frames runs open loop, which times the proxy's own cost
    proxy = build_proxy(ProxyConfig(upstream=str(CKPTS / "tinywam"), world_model=str(CKPTS / "wm_augmented"),
                                    device="cpu", errors="http"), planning={"policy": PlannedPolicyConfig(history="seen")})
    with BackgroundServer(create_app(load_wam(CKPTS / "tinywam", device="cpu"))) as direct, \
            BackgroundServer(create_proxy_app(proxy)) as srv:
        task = {"task_description": "insert the cube into the square hole"}
        ws = {with_frames: WebsocketClientPolicy(host=f"ws://{srv.host}:{srv.port}") for with_frames in (False, True)}
        for k in range(args.chunks):
            times["direct"].append(timed(direct.url + protocol.ROUTE, {**frame(rng, args.size), **task})[0])
            for robot, with_frames in (("blind", False), ("seeing", True)):
                extra = {}
                if with_frames and k:
                    extra["chunk_frames"] = {str(o): frame(rng, args.size) for o in (4, 8, 12)}
                dt, ans = timed(f"{srv.url}/s/{robot}/act", {**frame(rng, args.size), **task, **extra})
                reason = ans["wamplan"]["open_loop"]
                if k and with_frames:
                    assert reason is None, reason
                    times["proxy planned"].append(dt)
                elif k:
                    assert reason == "no-history", reason
                    times["proxy open loop"].append(dt)
            for with_frames, client in ws.items():
                extra = {"chunk_frames": {str(o): frame(rng, args.size) for o in (4, 8, 12)}} if with_frames and k else {}
                t0 = time.perf_counter()
                reason = client.infer({**frame(rng, args.size), **task, **extra})["wamplan"]["open_loop"]
                if k:
                    assert reason == (None if with_frames else "no-history"), reason
                    times["openpi planned" if with_frames else "openpi open loop"].append(time.perf_counter() - t0)
    proxy.close()
    print(f"{args.size}-px views, {args.chunks} chunks a kind (the first of an episode left out for the proxy)")
    for kind, ts in times.items():
        ms = [1000 * t for t in ts]
        print(f"  {kind:16s} p50 {statistics.median(ms):8.1f} ms   mean {statistics.mean(ms):8.1f} ms   n={len(ms)}")


if __name__ == "__main__":
    main()
