"""The one resumable training loop of wamplan (world-model predictor and decoder, TinyWAM).

A training run is a directory::

    RUN/checkpoint/     model.safetensors + config.json + training_state/   (``wamplan.checkpoint``)
    RUN/metrics.jsonl   one JSON object per logged step ("event": "step", every ``log_every_steps``)
                        and per epoch ("event": "epoch": epoch means, lr, samples/s, ``val/...``)

Every trainer hands :func:`fit` its model, a :class:`Batches` source, a ``step_fn(model, batch) ->
(loss, logs)``, an optimisation config (:class:`LoopConfig`), the config to store and the identity of
its data. The loop owns AdamW (decay on matrices only), warm-up + cosine per step, gradient clipping,
the progress bar, validation and logging at epoch ends (to metrics.jsonl, and through one
:class:`~wamplan.train_log.RunLog` to TensorBoard / W&B where the config's ``log`` names them), and saving (at
every epoch end, every ``save_every_steps``, on ``max_steps`` and on Ctrl-C).

One resume rule: a run is resumed only with the same data (the ``data`` identity: stores, episodes,
split) and the same config (except :data:`RUN_ONLY_FIELDS` of its ``train`` section and the keys a
trainer names as retired); anything else is refused with one line naming the difference. Resuming is
exact: the data order of epoch e is a permutation seeded by (seed, e), the loop skips the batches
already done, and weights, optimizer, scheduler, counters and the torch CPU RNG are restored. (A CUDA
RNG is not saved: with dropout on a GPU a resumed run differs from an uninterrupted one only in its
dropout masks.)
"""

from __future__ import annotations

import dataclasses
import json
import time
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, Protocol, Sequence

import torch
from torch import nn
from torch.utils.data import DataLoader, Dataset

from wamplan.checkpoint import (CKPT_DIR, CONFIG_FILE, STATE_DIR, has_training_state, load_training_state,
                                load_weights, read_config, save_checkpoint)
from wamplan.errors import UserError, checkpoint_kind, require_own_dir
from wamplan.locks import dir_lock
from wamplan.optim import make_adamw, optimizer_step, warmup_cosine
from wamplan.progress import progress_bar
from wamplan.train_log import RunLog, require_backends
from wamplan.train_config import PRECISIONS, RUN_ONLY_FIELDS, AdamWConfig, LoopConfig  # noqa: F401  (their home)

METRICS_FILE = "metrics.jsonl"

StepFn = Callable[[nn.Module, Any], tuple[torch.Tensor, dict[str, float]]]
Pictures = Callable[[nn.Module], dict[str, Any]]  # model -> {name: (H, W, 3) uint8 image}, e.g. prediction | target


class Batches(Protocol):
    """Where the batches come from: ``len`` items, and the batches of one epoch in a given item order."""

    def __len__(self) -> int: ...

    def epoch(self, indices: list[int], batch_size: int, first_step: int) -> Iterable[Any]:
        """Batches of ``batch_size`` items in the order ``indices`` (whole batches only); ``first_step`` is
        the global step of the first one (for per-step randomness such as augmentation)."""
        ...


class DatasetBatches:
    """Batches of a torch ``Dataset`` through a ``DataLoader`` (worker processes, pinned memory)."""

    def __init__(self, dataset: Dataset, num_workers: int = 0, pin_memory: bool = False) -> None:
        self.dataset, self.num_workers, self.pin_memory = dataset, num_workers, pin_memory

    def __len__(self) -> int:
        return len(self.dataset)  # type: ignore[arg-type]

    def epoch(self, indices: list[int], batch_size: int, first_step: int) -> Iterable[Any]:
        g = torch.Generator().manual_seed(first_step)  # worker seeds; keeps the global RNG untouched
        return DataLoader(self.dataset, batch_size=batch_size, sampler=indices, drop_last=True,
                          num_workers=self.num_workers, generator=g, pin_memory=self.pin_memory)


@dataclass
class FitResult:
    state: dict[str, Any]  # epoch, step_in_epoch, global_step
    metrics: dict[str, Any]  # the last epoch record (or the counters, with "stopped", when stopped mid-epoch)
    # every epoch record of the run, resumes included
    history: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    finished_before: bool = False  # the run had already done all its epochs: nothing was trained


# ------------------------------------------------------------------------------------------------ run directory
def run_paths(run_dir: str | Path) -> tuple[Path, Path]:
    """(checkpoint directory, metrics file) of a run directory."""
    run = Path(run_dir)
    return run / CKPT_DIR, run / METRICS_FILE


def check_run_dir(run_dir: str | Path, what: str = "a training run") -> None:
    """Refuse an ``--out`` that would mix a run with something else."""
    run = Path(run_dir)
    if run.exists() and not run.is_dir():
        raise UserError(f"--out {run} is a file; pass a directory for the training run")
    if (run / CONFIG_FILE).is_file():
        kind = checkpoint_kind(run)
        holds = f"a '{kind}' checkpoint" if kind else "a checkpoint"
        raise UserError(f"--out {run} holds {holds} (a checkpoint directory, not a run directory); it loads for "
                        f"inference as it is: train into a new --out")
    require_own_dir(run, (f"{CKPT_DIR}/", METRICS_FILE), what)


def saved_progress(run_dir: str | Path) -> dict[str, Any] | None:
    """The saved counters (epoch, step_in_epoch, global_step, ...) of a resumable run, else None."""
    ckpt, _ = run_paths(run_dir)
    if not has_training_state(ckpt):
        return None
    return json.loads((ckpt / STATE_DIR / "state.json").read_text())["train_state"]


def read_metrics(run_dir: str | Path, event: str | None = None) -> list[dict[str, Any]]:
    """The records of ``RUN/metrics.jsonl`` (only those of ``event`` if given). A torn last line (a kill mid-write)
    is skipped; any other line that is not a record (a JSON object with its ``global_step``) is one line naming
    the file and the line."""
    path = Path(run_dir) / METRICS_FILE if Path(run_dir).is_dir() else Path(run_dir)
    if not path.is_file():
        return []
    raw = path.read_bytes()
    lines = raw.split(b"\n")
    recs = []
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except ValueError:  # not JSON, or not UTF-8
            if n == len(lines):  # the last line, without its newline: cut by a kill mid-write
                break
            rec = None
        if not isinstance(rec, dict) or not isinstance(rec.get("global_step"), int):
            raise UserError(f"{path} line {n} is not a training metrics record (a JSON object with its global_step); "
                            f"pass a run directory of `wamplan wm train` or `wamplan wam train`, or its metrics.jsonl")
        recs.append(rec)
    return [r for r in recs if event is None or r.get("event", "epoch") == event]


def _short(v: Any, limit: int = 120) -> str:
    s = json.dumps(v)
    return s if len(s) <= limit else s[:limit - 3] + "..."


def _leaf_diff(saved: Any, now: Any, name: str, skip: Sequence[str] = ()) -> list[str]:
    if isinstance(saved, dict) and isinstance(now, dict):
        return [d for k in sorted(set(saved) | set(now)) if k not in skip
                for d in _leaf_diff(saved.get(k), now.get(k), k)]
    return [] if saved == now else [f"different {name}: saved {_short(saved)}, now {_short(now)}"]


def shown(task: str | None, cameras: Sequence[str] | None) -> dict[str, Any]:
    """What a checkpoint records of what its data showed (its config's ``data`` section, kept apart from the data
    identity a resumed run must match): ``{"task": ..., "cameras": [...]}``, each only where given."""
    return {**({"task": task} if task else {}), **({"cameras": list(cameras)} if cameras is not None else {})}


def check_data(run_dir: str | Path, kind: str, data: dict[str, Any]) -> None:
    """Half of the resume rule, cheap enough to run before loading anything: the same data as saved."""
    saved = json.loads(json.dumps(read_config(run_paths(run_dir)[0], kind).get("data") or {}))
    now = json.loads(json.dumps(data))
    diff = [d for k in sorted(now) for d in _leaf_diff(saved.get(k), now[k], k)]
    if diff:
        raise UserError(f"{run_dir} was trained on different data ({'; '.join(diff)}); resume it with the same "
                        f"--data or use another --out")


def check_resume(run_dir: str | Path, kind: str, config: dict[str, Any], data: dict[str, Any] | None,
                 retired: Mapping[str, Sequence[str]] | None = None) -> None:
    """The resume rule: the same data and the same config (but :data:`RUN_ONLY_FIELDS`) as the saved run.
    ``retired`` ({section: keys}): keys of the config's sections (``train``, ``predictor``, ...) that older runs of
    ``kind`` stored and this version no longer has (ignored)."""
    if data is not None:
        check_data(run_dir, kind, data)
    saved = json.loads(json.dumps(read_config(run_paths(run_dir)[0], kind)))
    now = json.loads(json.dumps(config))
    diff = []
    for section in sorted((set(saved) | set(now)) - {"data"}):
        skip = (*(RUN_ONLY_FIELDS if section == "train" else ()), *(retired or {}).get(section, ()))
        diff += _leaf_diff(saved.get(section), now.get(section), section, skip)
    if diff:
        raise UserError(f"{run_dir} was trained with a different config ({'; '.join(diff)}); re-run with the same "
                        f"options to resume it (only {', '.join(RUN_ONLY_FIELDS)} may change) or use another --out")


def _trim_metrics(path: Path, epoch: int, global_step: int) -> None:
    """Drop records logged after the checkpoint being resumed (a crash between a log line and a save)."""
    keep = [r for r in read_metrics(path) if r["global_step"] <= global_step
            and (r.get("event", "epoch") != "epoch" or r["epoch"] <= epoch)]
    path.write_text("".join(json.dumps(r) + "\n" for r in keep))


def _to_device(batch: Any, device: torch.device) -> Any:
    if isinstance(batch, dict):
        return {k: _to_device(v, device) for k, v in batch.items()}
    return batch.to(device, non_blocking=True) if torch.is_tensor(batch) else batch


# ------------------------------------------------------------------------------------------------ the loop
@contextmanager
def run_lock(run: Path) -> Iterator[None]:
    """Hold ``run``'s write lock (``run/.lock``, :func:`wamplan.locks.dir_lock`) while the block runs: one line if
    another process holds it, so two trainings never write one run (its metrics and checkpoint) at once."""
    with dir_lock(run, "trained"):
        yield


def fit(*args: Any, **kwargs: Any) -> FitResult:
    """:func:`train` under the run's write lock (:func:`run_lock`), taken before the run is first written."""
    with ExitStack() as held:
        return train(*args, hold=lambda run: held.enter_context(run_lock(run)), **kwargs)


def train(model: nn.Module, batches: Batches, step_fn: StepFn, cfg: LoopConfig, *, run_dir: str | Path, kind: str,
          config: dict[str, Any], data: dict[str, Any] | None = None, device: torch.device | None = None,
          evaluate: Callable[[nn.Module], dict[str, float]] | None = None,
          on_fresh_start: Callable[[], None] | None = None, resume: bool = False, max_steps: int | None = None,
          progress: bool = True, desc: str = "train", log: Callable[[str], None] | None = print,
          retired: Mapping[str, Sequence[str]] | None = None, hold: Callable[[Path], None] = lambda run: None,
          pictures: Pictures | None = None) -> FitResult:
    """Train ``model`` (already on ``device``) into ``run_dir`` with ``step_fn(model, batch) -> (loss, logs)``.

    ``config`` is stored in the checkpoint (``kind`` names the model family) with ``data`` (the identity
    of the training data, checked on resume) as its ``data`` section. ``evaluate(model)`` runs under
    no_grad in eval mode after every epoch; ``on_fresh_start`` runs only when not resuming (e.g. to
    compute normalisation statistics). ``resume`` continues the run's checkpoint (an error without it if
    one exists). ``max_steps`` stops after that many optimisation steps in all (saved; resumable).
    ``retired``: {section: keys} that older runs of ``kind`` stored and this version no longer has (see
    :func:`check_resume`). ``hold(run)`` is called before the run is first written (``fit`` takes its lock there).
    ``pictures(model)``: images logged (to the backends of ``cfg.log`` only) after each epoch's ``evaluate``.
    """
    run = Path(run_dir)
    ckpt, metrics_path = run_paths(run)
    device = device or next(model.parameters()).device
    say = log or (lambda _: None)
    if max_steps is not None and max_steps < 1:
        raise UserError(f"--max-steps {max_steps} must be at least 1 (optimisation steps in all); drop it to train "
                        f"every epoch")
    check_run_dir(run)
    require_backends(cfg.log)  # a missing logger package: one line before anything is trained
    bs, n = cfg.batch_size, len(batches)
    steps_per_epoch = n // bs
    if steps_per_epoch < 1:
        raise UserError(f"the training set has {n} items, fewer than batch_size {bs}; collect more data or lower "
                        f"--batch-size")
    if data is not None:
        config = dict(config, data={**(config.get("data") or {}), **data})
    betas = {"betas": cfg.betas} if isinstance(cfg, AdamWConfig) else {}
    opt = make_adamw(model, cfg.lr, cfg.weight_decay, **betas)
    sched = warmup_cosine(opt, round(cfg.warmup_epochs * steps_per_epoch), steps_per_epoch * cfg.epochs,
                          cfg.min_lr_ratio)
    state = {"epoch": 0, "step_in_epoch": 0, "global_step": 0}
    if (ckpt / CONFIG_FILE).is_file() and not has_training_state(ckpt):
        raise UserError(f"{ckpt} holds a checkpoint without training state, so it cannot be resumed; pass a new --out")
    if has_training_state(ckpt) and not resume:
        raise UserError(f"{run} already holds a training checkpoint; pass --resume to continue it or a new --out")
    if resume and has_training_state(ckpt):
        hold(run)
        check_resume(run, kind, config, data, retired)
        load_weights(ckpt, model, device)
        saved = load_training_state(ckpt, opt, sched)
        if saved.get("steps_per_epoch") != steps_per_epoch:
            raise UserError(f"{ckpt} was trained with {saved.get('steps_per_epoch')} steps per epoch, the data now "
                            f"give {steps_per_epoch}; resume with the same data and batch size or use another --out")
        state.update({k: saved[k] for k in state})
        torch.set_rng_state(torch.tensor(saved["rng_cpu"], dtype=torch.uint8))
        _trim_metrics(metrics_path, state["epoch"], state["global_step"])
        if state["epoch"] < cfg.epochs:
            say(f"resuming {run} at epoch {state['epoch'] + 1}, step {state['global_step']}")
    else:
        if on_fresh_start is not None:
            on_fresh_start()
        run.mkdir(parents=True, exist_ok=True)
        hold(run)
        if has_training_state(ckpt):  # another process began this run since the check above
            raise UserError(f"{run} already holds a training checkpoint; pass --resume to continue it or a new --out")
        metrics_path.write_text("")

    def save() -> None:
        ts = dict(state, rng_cpu=torch.get_rng_state().tolist(), steps_per_epoch=steps_per_epoch)
        save_checkpoint(ckpt, model, config, kind=kind, optimizer=opt, scheduler=sched, train_state=ts)

    def write(record: dict[str, Any]) -> None:
        with open(metrics_path, "a") as f:
            f.write(json.dumps(record) + "\n")
        curves.scalars(record)

    if state["epoch"] >= cfg.epochs:
        history = read_metrics(run, "epoch")
        if log is not None:  # a re-run of a finished command: say it was done, not only the last epoch's figures
            log(f"{run} has already finished {state['epoch']} epochs ({state['global_step']} steps); nothing to do. "
                f"Pass --epochs > {state['epoch']} to train longer, or a new --out.")
        return FitResult(dict(state), history[-1] if history else dict(state), history, finished_before=True)
    metrics: dict[str, Any] = {"epoch": state["epoch"], "global_step": state["global_step"]}
    curves = RunLog(cfg.log, run, kind, config, resume_step=state["global_step"])
    model.train()
    try:
        while state["epoch"] < cfg.epochs:
            epoch, start = state["epoch"], state["step_in_epoch"]
            g = torch.Generator().manual_seed(cfg.seed * 1_000_003 + epoch)
            order = torch.randperm(n, generator=g)[: steps_per_epoch * bs][start * bs:].tolist()
            bar = progress_bar(total=steps_per_epoch, initial=start, desc=f"{desc} {epoch + 1}/{cfg.epochs}",
                               disable=not progress, dynamic_ncols=True)
            sums: dict[str, float] = {}
            window: dict[str, float] = {}  # sums since the last step record
            count, window_n, t0, seen = 0, 0, time.perf_counter(), 0
            for batch in batches.epoch(order, bs, state["global_step"]):
                with torch.autocast(device.type, torch.bfloat16, enabled=cfg.precision == "bfloat16"):
                    loss, logs = step_fn(model, _to_device(batch, device))
                optimizer_step(model, opt, sched, loss, cfg.grad_clip)
                state["global_step"] += 1
                state["step_in_epoch"] += 1
                count, window_n, seen = count + 1, window_n + 1, seen + bs
                for k, v in (("loss", float(loss.detach())), *logs.items()):
                    sums[k] = sums.get(k, 0.0) + v
                    window[k] = window.get(k, 0.0) + v
                bar.update(1)
                bar.set_postfix({k: f"{v / count:.4g}" for k, v in sums.items()}
                                | {"sps": f"{seen / (time.perf_counter() - t0):.0f}",
                                   "lr": f"{sched.get_last_lr()[0]:.2e}"})
                if cfg.log_every_steps and state["global_step"] % cfg.log_every_steps == 0:
                    write({"event": "step", "epoch": epoch + 1, "global_step": state["global_step"],
                           "lr": sched.get_last_lr()[0], **{f"train/{k}": v / window_n for k, v in window.items()}})
                    window, window_n = {}, 0
                if cfg.save_every_steps and state["global_step"] % cfg.save_every_steps == 0:
                    save()
                if max_steps is not None and state["global_step"] >= max_steps:
                    break
            bar.close()
            if state["step_in_epoch"] < steps_per_epoch:  # stopped by max_steps inside the epoch
                save()
                say(f"stopped at step {state['global_step']} (max_steps); re-run the same command to continue")
                metrics = {"epoch": epoch, "global_step": state["global_step"], "stopped": "max_steps"}
                return FitResult(dict(state), metrics, read_metrics(run, "epoch"))
            state["epoch"], state["step_in_epoch"] = epoch + 1, 0
            metrics = {"event": "epoch", "epoch": epoch + 1, "global_step": state["global_step"],
                       "lr": sched.get_last_lr()[0], **{f"train/{k}": v / max(1, count) for k, v in sums.items()},
                       "samples_per_s": seen / max(1e-9, time.perf_counter() - t0)}
            if evaluate is not None:
                with evaluating(model), torch.no_grad():
                    metrics.update({f"val/{k}": v for k, v in evaluate(model).items()})
            write(metrics)
            if pictures is not None and cfg.log:
                with evaluating(model), torch.no_grad():
                    curves.images(pictures(model), state["global_step"])
            save()
            say(f"{desc} epoch {epoch + 1}: " + " ".join(f"{k}={v:.4g}" for k, v in metrics.items()
                                                         if isinstance(v, float) and k != "lr"))
            if max_steps is not None and state["global_step"] >= max_steps:
                return FitResult(dict(state), dict(metrics, stopped="max_steps"), read_metrics(run, "epoch"))
    except KeyboardInterrupt:
        save()
        say(f"interrupted: checkpoint saved at step {state['global_step']}; re-run the same command to resume")
        raise
    finally:
        curves.close()
    return FitResult(dict(state), metrics, read_metrics(run, "epoch"))


@contextmanager
def evaluating(model: nn.Module) -> Iterator[nn.Module]:
    """``model`` in eval mode inside the block (validation, scoring); the mode it had is restored after, on an
    error too."""
    was_training = model.training
    model.eval()
    try:
        yield model
    finally:
        model.train(was_training)
