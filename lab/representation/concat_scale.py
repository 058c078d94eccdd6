"""The factor a ``concat`` part needs for the planning cost to weigh it as much as the first part, per dim.

(``concat``, ``task-cnn`` and the frame reader this script uses, ``data.readers.StateFrames``, left the core at stop 78:
it runs at commit 9c6eb5d or earlier; lab/representation/README.md.)

    python lab/representation/concat_scale.py STORES '{"name": "task-cnn", "ckpt": "enc16"}' [--base JSON]

The planning cost is a plain mean over dims of squared differences, so what a part weighs is its per-dim
variance. Over every stored frame of STORES (comma separated; all views, all tokens) the script prints each
encoder's per-dim variance (each dim's variance over tokens, averaged over dims) and the factor
sqrt(base's / part's) that equalises them: the part's ``scales`` entry. ``--base`` defaults to the ``mini``
preset's encoder (patch-pixels).
"""

from __future__ import annotations

import argparse
import json

import torch

from wamplan.errors import UserError, run_script


class DimMoments:
    """Running per-dim sums of tokens (..., D) -> per-dim variance, averaged over dims."""

    def __init__(self) -> None:
        self.n, self.s, self.ss = 0, 0.0, 0.0

    def add(self, z: torch.Tensor) -> None:
        z = z.reshape(-1, z.shape[-1]).double()  # (tokens, D)
        self.n, self.s, self.ss = self.n + len(z), self.s + z.sum(0), self.ss + z.square().sum(0)

    def variance(self) -> float:
        mean = self.s / self.n
        return float((self.ss / self.n - mean.square()).mean())


def main(argv: list[str] | None = None) -> None:
    from wamplan.data.readers import StateFrames
    from wamplan.presets import get_world_model_preset
    from wamplan.progress import progress_bar
    from wamplan.worldmodel.stores import frozen_encoder

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("stores", help="episode stores, comma separated")
    p.add_argument("part", help="the part's encoder config as JSON, with its name")
    p.add_argument("--base", default=None, help="the first part's encoder config as JSON (default: the mini preset's)")
    args = p.parse_args(argv)
    example = '\'{"name": "task-cnn", "ckpt": DIR}\''
    try:
        part, base = json.loads(args.part), json.loads(args.base) if args.base else None
    except json.JSONDecodeError as e:
        raise UserError(f"an encoder config is not JSON ({e}); e.g. {example}") from None
    for config in (part, base):
        if config is not None and not (isinstance(config, dict) and config.get("name")):
            raise UserError(f"an encoder config is a JSON object with its \"name\", got {config!r}; e.g. {example}")
    if base is None:
        preset = get_world_model_preset("mini")
        base = {"name": preset.encoder, **preset.encoder_kwargs}
    encoders = [frozen_encoder(c.pop("name"), c, device="cpu") for c in (dict(base), dict(part))]
    frames = StateFrames(args.stores.split(","), split="all")
    moments = [DimMoments() for _ in encoders]
    for i in progress_bar(range(len(frames)), desc="frames"):
        images = frames[i]["images"]  # (V, H, W, 3)
        for enc, m in zip(encoders, moments):
            m.add(enc.encode(images))  # (V, N, D)
    vb, vp = (m.variance() for m in moments)
    if not vp > 0:
        raise UserError(f"the part's tokens do not vary over the {len(frames)} frames (variance {vp}); no scale "
                        f"equalises a constant part")
    print(json.dumps({"frames": len(frames), "base_variance": vb, "part_variance": vp, "scale": (vb / vp) ** 0.5}))


if __name__ == "__main__":
    run_script(main, "concat_scale")
