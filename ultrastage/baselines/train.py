"""Training and testing AlbedoNet / NormalNet on a release's relighting set (``ultrastage train``).

``train(release, config, out_dir)`` trains on the ``train`` split with the MSE on the masked pixels (as the
paper; the AlbedoNet's in linear space, on its albedo before the clip to [0, 1]), then measures the ``test``
split (:mod:`ultrastage.baselines.metrics`) for the network and the trivial baselines. Everything goes into
``out_dir`` (default :func:`default_out_dir`, beside the release, never in it):

* ``checkpoint.pt``: ``{format, format_version, network, config, step, model, optimizer, losses}``, written
  atomically (temporary file, then rename) every ``checkpoint_every`` steps and at the end; a run finding one
  resumes from it (same network and same config up to :attr:`TrainConfig.not_in_key`, else an error);
* ``config.yaml`` (the resolved config), ``loss.png`` (the loss curve);
* ``test_metrics.parquet`` (table ``baseline_metrics`` of :mod:`manifests.schemas`).

Step ``s`` draws its examples, crops and flips from ``numpy.random.default_rng([seed, s])``, so a resumed
run trains exactly as an uninterrupted one would (on the CPU, up to float summation order).
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.config import dump_yaml, from_dict, key_fields, to_dict
from pipeline.errors import ConfigError, InputError

from . import metrics
from .config import NETWORKS, TrainConfig
from .data import RelightDataset, open_relight_set
from .models import UNet, build_network, predict_image

__all__ = ["CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "CHECKPOINT_NAME", "METRICS_NAME", "TrainResult",
           "default_out_dir", "select_device", "read_checkpoint", "load_network", "masked_mse", "train",
           "evaluate", "comparison"]

CHECKPOINT_FORMAT = "ultrastage-baseline"
"""The ``format`` field of a baseline checkpoint."""
CHECKPOINT_VERSION = 2
"""Bumped when the checkpoint's contents or the networks' layers change; other versions are refused.
Version 2: the AlbedoNet predicts a shading correction of the linearised photo (with a global gain layer)
instead of a sigmoid albedo."""
CHECKPOINT_NAME = "checkpoint.pt"
METRICS_NAME = "test_metrics.parquet"
TRIVIAL_METHOD = {"albedonet": "input_image", "normalnet": "constant_normal"}
"""The trivial baseline each network is compared with (ultrastage.baselines.metrics)."""


@dataclass
class TrainResult:
    """What :func:`train` did and where it wrote."""

    out_dir: Path
    """Folder of the checkpoint, config, loss curve and metrics."""
    checkpoint: Path
    """The checkpoint file."""
    step: int
    """Steps the checkpoint has trained."""
    steps_run: int
    """Steps run by this call (0 when the checkpoint had already reached ``config.steps``)."""
    seconds: float
    """Wall-clock seconds of this call's training."""
    metrics: list[dict] = field(default_factory=list)
    """Rows of the ``baseline_metrics`` table written (empty when not evaluated)."""


def default_out_dir(release: str | Path, network: str) -> Path:
    """``<release>.baselines/<network>/`` beside the release folder (like ``<release>.work``)."""
    release = Path(release).resolve()
    return release.parent / f"{release.name}.baselines" / network


def select_device(name: str) -> torch.device:
    """'auto' -> CUDA when torch sees it, else CPU; 'cuda' when there is none is a ConfigError."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device 'cuda': torch sees no CUDA device (use 'auto' or 'cpu')")
    return torch.device(name)


def read_checkpoint(path: str | Path, network: str | None = None) -> dict[str, Any]:
    """A baseline checkpoint's dict, with ``config`` as a :class:`TrainConfig`.

    Raises:
        InputError: a missing or unreadable file, not a baseline checkpoint, another format version, or
            (``network`` given) another network's checkpoint.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "checkpoint not found")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many kinds for a corrupt or foreign file
        raise InputError(path, f"not a readable checkpoint: {type(error).__name__}: {error}") from error
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise InputError(path, f"not an UltraStage baseline checkpoint (format {CHECKPOINT_FORMAT!r} expected)")
    if ckpt.get("format_version") != CHECKPOINT_VERSION:
        raise InputError(path, f"checkpoint format version {ckpt.get('format_version')!r}; this code reads "
                               f"version {CHECKPOINT_VERSION} (retrain, or use the code that wrote it)")
    if ckpt.get("network") not in NETWORKS:
        raise InputError(path, f"checkpoint of an unknown network {ckpt.get('network')!r}")
    if network is not None and ckpt["network"] != network:
        raise InputError(path, f"checkpoint of {ckpt['network']}, not of {network}")
    try:
        ckpt["config"] = from_dict(TrainConfig, dict(ckpt["config"]), where=f"{path}: config")
    except (ConfigError, KeyError, TypeError) as error:
        raise InputError(path, f"checkpoint config unreadable: {error}") from error
    return ckpt


def load_network(path: str | Path, network: str | None = None,
                 device: torch.device | str = "cpu") -> tuple[UNet, dict[str, Any]]:
    """The trained network of a checkpoint (eval mode, on ``device``) and the checkpoint (see
    :func:`read_checkpoint`)."""
    ckpt = read_checkpoint(path, network)
    model = build_network(ckpt["config"])
    try:
        model.load_state_dict(ckpt["model"])
    except (RuntimeError, KeyError) as error:
        raise InputError(path, f"weights do not fit the {ckpt['network']} of its config: {error}") from error
    return model.to(device).eval(), ckpt


def masked_mse(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean squared error over the masked pixels and channels: pred, target (B, C, H, W), mask (B, 1, H, W)."""
    count = mask.sum() * pred.shape[1]
    return ((pred - target) ** 2 * mask).sum() / count.clamp(min=1.0)


def _save_atomic(path: Path, write) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _save_checkpoint(path: Path, model: UNet, optimizer: torch.optim.Optimizer, config: TrainConfig,
                     step: int, losses: list[float]) -> None:
    state = {"format": CHECKPOINT_FORMAT, "format_version": CHECKPOINT_VERSION, "network": config.network,
             "config": to_dict(config), "step": step, "model": model.state_dict(),
             "optimizer": optimizer.state_dict(), "losses": list(losses)}
    _save_atomic(path, lambda tmp: torch.save(state, tmp))


def _save_loss_curve(path: Path, losses: list[float], network: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    steps = np.arange(1, len(losses) + 1)
    ax.plot(steps, losses, lw=0.6, alpha=0.5, label="step")
    if len(losses) >= 10:
        k = max(len(losses) // 50, 5)
        smooth = np.convolve(losses, np.ones(k) / k, mode="valid")
        ax.plot(steps[k - 1:], smooth, lw=1.5, label=f"mean of {k}")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("masked MSE")
    ax.set_title(f"{network} training loss")
    ax.legend()
    fig.tight_layout()
    _save_atomic(path, lambda tmp: fig.savefig(tmp, format="png"))
    plt.close(fig)


def _check_resumable(ckpt: dict[str, Any], config: TrainConfig, path: Path) -> None:
    old, new = key_fields(ckpt["config"]), key_fields(config)
    changed = sorted(k for k in new if old.get(k) != new[k])
    if changed:
        diffs = ", ".join(f"{k}: {old.get(k)!r} -> {new[k]!r}" for k in changed)
        raise ConfigError(f"{path}: the checkpoint was trained with another config ({diffs}); "
                          "use another --out or remove the checkpoint")


def _progress(total: int, start: int, label: str):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, \
        TimeRemainingColumn

    progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                        TextColumn("loss {task.fields[loss]}"), TimeElapsedColumn(), TimeRemainingColumn())
    task = progress.add_task(label, total=total, completed=start, loss="-")
    return progress, task


def train(release: str | Path, config: TrainConfig, out_dir: str | Path | None = None, evaluate_test: bool = True,
          log=print) -> TrainResult:
    """Train ``config.network`` on the release's train split (resuming from ``out_dir``'s checkpoint), then
    measure the test split. Everything is checked before anything is written.

    Raises:
        InputError: no relighting set, an empty train or test split, a checkpoint of another network or
            format version. ConfigError: a checkpoint trained with another config. ValueError: the loss went
            NaN or Inf (the last checkpoint stays).
    """
    release_set = open_relight_set(release, ("train", "test") if evaluate_test else ("train",))
    out_dir = Path(out_dir) if out_dir is not None else default_out_dir(release_set.root, config.network)
    ckpt_path = out_dir / CHECKPOINT_NAME
    ckpt = read_checkpoint(ckpt_path, config.network) if ckpt_path.exists() else None
    if ckpt is not None:
        _check_resumable(ckpt, config, ckpt_path)
    device = select_device(config.device)
    if config.threads:
        torch.set_num_threads(config.threads)
    dataset = RelightDataset(release_set, "train", crop=config.crop, flip=config.flip,
                             cache=config.cache_examples)

    torch.manual_seed(config.seed)
    model = build_network(config).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    step, losses = 0, []
    if ckpt is not None:
        model.load_state_dict(ckpt["model"])
        optimizer.load_state_dict(ckpt["optimizer"])
        step, losses = int(ckpt["step"]), [float(x) for x in ckpt["losses"]]
        log(f"resuming {ckpt_path} at step {step}")

    out_dir.mkdir(parents=True, exist_ok=True)
    _save_atomic(out_dir / "config.yaml", lambda tmp: tmp.write_text(dump_yaml(config)))
    target_key = "albedo" if config.network == "albedonet" else "normal"
    first, t0 = step, time.perf_counter()
    if step < config.steps:
        progress, task = _progress(config.steps, step, f"{config.network} ({device.type})")
        with progress:
            model.train()
            while step < config.steps:
                rng = np.random.default_rng([config.seed, step])
                items = [dataset.example(int(i), rng) for i in rng.integers(0, len(dataset), config.batch_size)]
                batch = {k: torch.stack([it[k] for it in items]).to(device) for k in ("image", target_key, "mask")}
                loss = masked_mse(model.training_output(batch["image"]), batch[target_key], batch["mask"])
                if not torch.isfinite(loss):
                    raise ValueError(f"{ckpt_path}: training loss is {loss.item()} at step {step} (lower lr?); "
                                     "the last checkpoint is kept")
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                step += 1
                losses.append(float(loss.item()))
                progress.update(task, completed=step, loss=f"{losses[-1]:.5f}")
                if step % config.checkpoint_every == 0 or step == config.steps:
                    _save_checkpoint(ckpt_path, model, optimizer, config, step, losses)
        _save_loss_curve(out_dir / "loss.png", losses, config.network)
    seconds = time.perf_counter() - t0
    result = TrainResult(out_dir, ckpt_path, step, step - first, seconds)
    if evaluate_test:
        result.metrics = evaluate(release_set, ckpt_path, out_dir / METRICS_NAME, device=device, log=log)
    return result


def _rows(network: str, method: str, example_id: str, values: dict[str, float], step: int) -> list[dict]:
    return [{"network": network, "method": method, "split": "test", "example_id": example_id, "metric": k,
             "value": float(v), "step": step} for k, v in values.items()]


def evaluate(release: str | Path, checkpoint: str | Path, out_path: str | Path | None = None,
             split: str = "test", device: torch.device | str = "cpu", log=print) -> list[dict]:
    """Metrics of a checkpoint and of its trivial baseline on ``split`` (per example and over the split,
    ``example_id`` '*'), written as a ``baseline_metrics`` Parquet file at ``out_path`` when given.

    Raises:
        InputError: see :func:`open_relight_set` and :func:`read_checkpoint`.
    """
    from manifests import write_standalone_table

    release_set = open_relight_set(release, (split,))
    model, ckpt = load_network(checkpoint, device=device)
    network, step = ckpt["network"], int(ckpt["step"])
    trivial = TRIVIAL_METHOD[network]
    dataset = RelightDataset(release_set, split)
    rows: list[dict] = []
    per_method: dict[str, list[dict[str, float]]] = {network: [], trivial: []}
    angles: dict[str, list[np.ndarray]] = {network: [], trivial: []}
    for i, example_id in enumerate(dataset.example_ids):
        arrays = dataset.arrays(i)
        mask = arrays["mask"]
        if not mask.any():
            log(f"  {example_id}: empty mask, left out")
            continue
        pred = predict_image(model, arrays["image"], device)
        if network == "albedonet":
            preds = {network: pred, trivial: metrics.input_image_albedo(arrays["image"])}
            for method, p in preds.items():
                values = metrics.albedo_metrics(p, arrays["albedo"], mask)
                per_method[method].append(values)
                rows += _rows(network, method, example_id, values, step if method == network else 0)
        else:
            preds = {network: pred, trivial: metrics.constant_normal(*mask.shape)}
            for method, p in preds.items():
                a = metrics.normal_angles(p, arrays["normal"], mask)
                angles[method].append(a)
                rows += _rows(network, method, example_id, metrics.normal_summary(a),
                              step if method == network else 0)
    if not rows:
        raise InputError(release_set.root / "manifests" / "relight_examples.parquet",
                         f"no example of the {split} split has a non-empty mask")
    for method in (network, trivial):
        method_step = step if method == network else 0
        if network == "albedonet":
            names = sorted({k for v in per_method[method] for k in v})
            overall = {k: float(np.mean([v[k] for v in per_method[method] if k in v])) for k in names}
        else:
            overall = metrics.normal_summary(np.concatenate(angles[method]))
        rows += _rows(network, method, "*", overall, method_step)
    rows = [dict(r, split=split) for r in rows]
    if out_path is not None:
        write_standalone_table(out_path, "baseline_metrics", rows)
    log(comparison(rows))
    return rows


_COLUMNS = {
    "albedonet": [("albedo_psnr_raw_db", "PSNR raw dB", 2), ("albedo_psnr_scaled_db", "PSNR scaled dB", 2),
                  ("albedo_ssim_raw", "SSIM raw", 4), ("albedo_ssim_scaled", "SSIM scaled", 4),
                  ("albedo_rmse_raw", "RMSE raw", 4), ("albedo_rmse_scaled", "RMSE scaled", 4)],
    "normalnet": [("normal_mean_deg", "mean °", 2), ("normal_median_deg", "median °", 2),
                  ("normal_under_11_25_pct", "<11.25° %", 1), ("normal_under_22_5_pct", "<22.5° %", 1),
                  ("normal_under_30_pct", "<30° %", 1)],
}


def comparison(rows: list[dict]) -> str:
    """A plain-text table of the split-wide ('*') metrics of every method in ``rows``."""
    overall = [r for r in rows if r["example_id"] == "*"]
    if not overall:
        return "(no metrics)"
    network = overall[0]["network"]
    methods = list(dict.fromkeys(r["method"] for r in overall))
    cols = _COLUMNS[network]
    split = overall[0]["split"]
    n = len({r["example_id"] for r in rows if r["example_id"] != "*"})
    header = f"{'method':<16}" + "".join(f"{label:>16}" for _, label, _ in cols)
    lines = [f"{network} on the {split} split ({n} examples, masked pixels; 'scaled': per-channel "
             f"least-squares scale first)" if network == "albedonet" else
             f"{network} on the {split} split ({n} examples, masked pixels, camera frame)", header]
    for method in methods:
        values = {r["metric"]: r["value"] for r in overall if r["method"] == method}
        cells = "".join(f"{values[k]:>16.{d}f}" if k in values else f"{'-':>16}" for k, _, d in cols)
        lines.append(f"{method:<16}{cells}")
    return "\n".join(lines)
