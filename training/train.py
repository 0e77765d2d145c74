"""Training loops of the learned inverse transform (Price et al. 2022, Sec. 3.2 (b)) and its baseline.

1. the VAE (``training.vae``) on unlabeled lab frames;
2. the regressor (``training.regressor``) on renders passed through the frozen encoder;
3. the direct CNN (``training.direct``) end to end on the same renders.

Deterministic by seed on the CPU (fixed thread count, deterministic algorithms, seeded shuffles).
Inputs are normalised once by the same ``Normalise`` module the exported graphs contain.
"""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from importlib.metadata import version
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from service.errors import MeniscopeError
from service.inverse.manifest import (
    AUTOENCODER_OUTPUTS,
    InputSpec,
    Manifest,
    MethodEntry,
    TrainingSummary,
    load_manifest,
    prepare_model_folder,
    write_manifest,
)
from service.plotting import pyplot
from service.recordings.roi import read_roi_frames
from service.scene import Scene
from service.validation.truth import oscillation_truth, read_truth, score
from training.dataset import Dataset, DatasetConfig, Jitter, generate, open_dataset
from training.direct import DirectCNN
from training.export import export_onnx, expose_latent, parity
from training.normalise import Normalise, downsample_factor
from training.regressor import Head, LatentRegressor, targets
from training.vae import VAE, Encoder, NetConfig, Reconstruction, vae_loss
from training.warmstart import load_warm_start

#: What each exported method is, for the manifest.
DESCRIPTIONS = {
    "network": "VAE encoder (trained on lab frames) + regressor (trained on renders), Price et al. 2022 Sec. 3.2 (b)",
    "direct": "CNN trained end to end on renders: the baseline Sec. 3.2 argued against",
    "autoencoder": "VAE (trained on lab frames): frames -> normalised input and its reconstruction, for figures",
}
History = dict[str, list[float]]  # "train", "val": mean loss per epoch
#: Frames per chunk when normalising, encoding or predicting outside the optimiser (bounds memory).
CHUNK = 4096


@dataclass(frozen=True)
class TrainConfig:
    """Everything that determines the trained models; stored whole in the model manifest."""

    net: NetConfig = field(default_factory=NetConfig)
    seed: int = 0
    threads: int = 2
    samples: int = 50_000  # renders generated when no dataset is given
    lab_frames: int = 20_000  # at most this many lab frames, in evenly spaced runs
    val_fraction: float = 0.1  # of the renders and of the lab frames, held out
    input_dtype: str = "uint16"  # stored pixel type of the exported graphs (uint16 also takes uint8)
    beta: float = 1.0  # KL weight of the VAE objective
    batch: int = 256
    vae_epochs: int = 12
    vae_lr: float = 2e-3
    regressor_epochs: int = 60
    regressor_lr: float = 3e-3
    direct_epochs: int = 12
    direct_lr: float = 2e-3
    init: str | None = None  # model folder the weights start from (``--init``); None: random
    #: the scene's calibration's open parameters, drawn over their ranges in every chunk of renders (``Jitter``)
    open_ranges: dict[str, tuple[float, float]] = field(default_factory=dict)

    @classmethod
    def quick(cls) -> TrainConfig:
        """A run of seconds for tests and smoke checks; the models it makes are not useful."""
        return cls(samples=1536, lab_frames=1024, vae_epochs=2, regressor_epochs=4, direct_epochs=2)

    @classmethod
    def fine_tune(cls, init: Path) -> TrainConfig:
        """Starting from ``init``'s weights: a fifth of the renders, a quarter of the epochs, smaller steps."""
        return cls(
            samples=10_000,
            vae_epochs=3,
            vae_lr=5e-4,
            regressor_epochs=15,
            regressor_lr=1e-3,
            direct_epochs=3,
            direct_lr=5e-4,
            init=str(init),
        )


def seed_everything(seed: int, threads: int) -> torch.Generator:
    """Seed torch, fix the thread count, insist on deterministic kernels; returns the shuffling generator."""
    torch.manual_seed(seed)
    torch.set_num_threads(threads)
    torch.use_deterministic_algorithms(True)
    return torch.Generator().manual_seed(seed)


@torch.no_grad()
def in_chunks(
    fn: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor | np.ndarray, desc: str | None = None
) -> torch.Tensor:
    """``fn`` applied to ``x`` in chunks of :data:`CHUNK` rows (numpy input copied per chunk: it may be a read-only map)."""
    parts = []
    for start in tqdm(range(0, len(x), CHUNK), desc=desc, unit="chunk", disable=None if desc else True):
        part = x[start : start + CHUNK]
        parts.append(fn(torch.from_numpy(np.array(part)) if isinstance(part, np.ndarray) else part))
    return torch.cat(parts)


def split(n: int, val_fraction: float, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Shuffled train and validation indices of ``n`` items (at least one of each)."""
    order = torch.randperm(n, generator=generator)
    n_val = min(n - 1, max(1, round(n * val_fraction)))
    return order[n_val:].sort().values, order[:n_val].sort().values


def fit(
    model: nn.Module,
    loss: Callable[[torch.Tensor], torch.Tensor],
    val_loss: Callable[[], float],
    n_train: int,
    epochs: int,
    batch: int,
    lr: float,
    generator: torch.Generator,
    desc: str,
) -> History:
    """AdamW over ``epochs`` shuffled passes; learning rate: 5 % linear warm-up, then cosine to zero.

    ``loss(indices)`` is the mean loss of those training items; ``val_loss()`` is evaluated after
    each epoch with the model in eval mode and gradients off.
    """
    params = [p for p in model.parameters() if p.requires_grad]
    optimiser = torch.optim.AdamW(params, lr=lr, weight_decay=1e-4)
    steps = epochs * math.ceil(n_train / batch)
    warm = max(1, steps // 20)
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimiser, lambda s: min(1.0, (s + 1) / warm) * 0.5 * (1 + math.cos(math.pi * min(s, steps) / steps))
    )
    history: History = {"train": [], "val": []}
    with tqdm(total=steps, desc=desc, unit="batch", disable=None) as bar:
        for _ in range(epochs):
            model.train()
            total = 0.0
            for idx in torch.randperm(n_train, generator=generator).split(batch):
                value = loss(idx)
                optimiser.zero_grad(set_to_none=True)
                value.backward()
                optimiser.step()
                schedule.step()
                total += value.item() * len(idx)
                bar.update()
            model.eval()
            with torch.no_grad():
                history["val"].append(float(val_loss()))
            history["train"].append(total / n_train)
            bar.set_postfix(train=f"{history['train'][-1]:.4g}", val=f"{history['val'][-1]:.4g}")
    model.eval()
    return history


def train_vae(
    lab: torch.Tensor, config: TrainConfig, generator: torch.Generator, start: VAE | None = None
) -> tuple[VAE, History]:
    """The VAE on normalised lab frames (N, 1, h, w); loss: negative ELBO per frame (Sec. 3.2 (b)).

    ``start``: a VAE to train further (a warm start), else a new one."""
    train_idx, val_idx = split(len(lab), config.val_fraction, generator)
    vae = start if start is not None else VAE(config.net, lab.shape[2], lab.shape[3])

    def loss(idx: torch.Tensor) -> torch.Tensor:
        x = lab[train_idx[idx]]  # (B, 1, h, w)
        return vae_loss(x, *vae(x), config.beta)[0]

    def val_loss() -> float:
        x = lab[val_idx]
        return vae_loss(x, *vae(x), config.beta)[0].item()

    history = fit(vae, loss, val_loss, len(train_idx), config.vae_epochs, config.batch, config.vae_lr, generator, "VAE")
    return vae, history


def target_scale(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column mean and standard deviation (N, 5) -> (5,), (5,); a constant column gets std 1."""
    std = y.std(axis=0)
    return y.mean(axis=0), np.where(std > 0, std, 1.0)


def standardised_mse(head: Head, pred: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Mean squared error over the five targets, each in units of its training-set std."""
    return (head.standardise(pred) - head.standardise(y)).pow(2).mean()


def train_regressor(
    encoder: Encoder,
    renders: torch.Tensor,
    y: torch.Tensor,
    train_idx: torch.Tensor,
    val_idx: torch.Tensor,
    config: TrainConfig,
    generator: torch.Generator,
    start: Head | None = None,
) -> tuple[Head, History]:
    """The head on encoder means of normalised renders (N, 1, h, w); targets ``y`` (N, 5), :data:`TARGETS`.

    The encoder is frozen (Sec. 3.2 (b)), so the means are computed once. ``start``: a head to train further
    (its target scale kept), else a new one scaled to these targets.
    """
    encoder.eval().requires_grad_(False)
    mu = in_chunks(lambda x: encoder(x)[0], renders, "encode renders")  # (N, latent)
    head = (
        start if start is not None else Head(config.net.latent, config.net.hidden, *target_scale(y[train_idx].numpy()))
    )
    history = fit(
        head,
        lambda idx: standardised_mse(head, head(mu[train_idx[idx]]), y[train_idx[idx]]),
        lambda: standardised_mse(head, head(mu[val_idx]), y[val_idx]).item(),
        len(train_idx),
        config.regressor_epochs,
        config.batch,
        config.regressor_lr,
        generator,
        "regressor",
    )
    return head, history


def train_direct(
    normalise: Normalise,
    renders: torch.Tensor,
    y: torch.Tensor,
    train_idx: torch.Tensor,
    val_idx: torch.Tensor,
    config: TrainConfig,
    generator: torch.Generator,
    start: DirectCNN | None = None,
) -> tuple[DirectCNN, History]:
    """The direct CNN end to end on normalised renders (N, 1, h, w); the baseline Sec. 3.2 argued against.

    ``start``: a direct CNN to train further (its target scale kept), else a new one."""
    h, w = renders.shape[2], renders.shape[3]
    model = start if start is not None else DirectCNN(config.net, normalise, h, w, *target_scale(y[train_idx].numpy()))

    def val_loss() -> float:
        pred = in_chunks(model.predict, renders[val_idx])
        return standardised_mse(model.head, pred, y[val_idx]).item()

    history = fit(
        model,
        lambda idx: standardised_mse(model.head, model.predict(renders[train_idx[idx]]), y[train_idx[idx]]),
        val_loss,
        len(train_idx),
        config.direct_epochs,
        config.batch,
        config.direct_lr,
        generator,
        "direct CNN",
    )
    return model, history


def plot_losses(histories: dict[str, History], path: Path) -> Path:
    """One panel per model: training and validation loss per epoch (log scale), as a PNG."""
    plt = pyplot()

    fig, axes = plt.subplots(1, len(histories), figsize=(4 * len(histories), 3.2), squeeze=False)
    for ax, (name, history) in zip(axes[0], histories.items()):
        epochs = np.arange(1, len(history["train"]) + 1)
        ax.plot(epochs, history["train"], label="train")
        ax.plot(epochs, history["val"], label="validation")
        ax.set(title=name, xlabel="epoch", yscale="log")
        ax.legend()
    axes[0][0].set_ylabel("loss")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def plot_validation(results: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]], path: Path) -> Path:
    """Predicted against true D(0, t): one row per data set, one column per method, as a PNG.

    ``results[data set][method]`` is (predictions, truths), each (N, 5) in :data:`TARGETS` order.
    """
    plt = pyplot()

    rows, cols = len(results), max(len(r) for r in results.values())
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.4 * rows), squeeze=False)
    for row, (data, by_method) in zip(axes, results.items()):
        for ax, (method, (pred, true)) in zip(row, by_method.items()):
            s = score(pred, true)
            ax.plot(true[:, 4] * 1e3, pred[:, 4] * 1e3, ",", alpha=0.5)
            lo, hi = np.percentile(true[:, 4] * 1e3, [0, 100])
            ax.plot([lo, hi], [lo, hi], "k-", lw=0.8)
            ax.set(
                title=f"{method}, {data}: RMSE {s.rmse['centre'] * 1e3:.2f} um",
                xlabel="true D(0) (um)",
                ylabel="predicted D(0) (um)",
            )
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def _open_or_render(scene: Scene, folder: Path | None, scratch: Path, config: TrainConfig, bit_depth: int) -> Dataset:
    """The renders: ``folder`` if it holds a dataset for this scene, else ``config.samples`` new ones there
    (or in ``scratch`` when no folder is given), quantised to the lab camera's ``bit_depth``."""
    if folder is not None and (folder / "manifest.json").exists():
        return open_dataset(folder, scene)
    target = folder if folder is not None else scratch / "renders"
    generate(
        DatasetConfig(
            scene=scene,
            samples=config.samples,
            seed=config.seed,
            bit_depth=bit_depth,
            jitter=Jitter(open_ranges=config.open_ranges),
        ),
        target,
        workers=config.threads,
    )
    return open_dataset(target, scene)


def _predict(model: nn.Module, frames: np.ndarray) -> np.ndarray:
    """Targets (N, 5) of stored frames (N, H, W), through a whole inverse network in torch."""
    return in_chunks(lambda f: torch.column_stack(model(f)), frames).numpy()


def train_models(
    scene: Scene,
    lab_video: Path,
    out: Path,
    config: TrainConfig,
    dataset: Path | None = None,
    holdout_video: Path | None = None,
) -> Manifest:
    """Everything ``meniscope train`` does: train, validate, export and describe the models in ``out``.

    ``dataset``: a folder of renders to use (or to create, with ``config.samples``); without it the
    renders go to a temporary folder. ``holdout_video``: a simulated recording (with its
    ``.truth.json``) that no model saw, scored as the "recording" validation set. ``config.init``: a model
    folder (of any scene) whose weights the three networks start from (``training.warmstart``).
    """
    started = time.perf_counter()
    if holdout_video is not None and holdout_video.resolve() == lab_video.resolve():
        raise MeniscopeError(holdout_video, "the hold-out recording must differ from the lab video the VAE learns")
    height, width = scene.camera.height_px, scene.camera.width_px
    normalise = Normalise(downsample_factor(scene, config.net.input_px))
    warm = None if config.init is None else load_warm_start(Path(config.init), config.net, normalise, height, width)
    prepare_model_folder(out)
    generator = seed_everything(config.seed, config.threads)
    lab_frames, lab_facts = read_roi_frames(lab_video, scene, config.lab_frames)
    with tempfile.TemporaryDirectory(prefix="meniscope-train-") as scratch:
        renders = _open_or_render(scene, dataset, Path(scratch), config, lab_facts["bit_depth"])
        x = in_chunks(normalise, renders.frames, "normalise renders")  # (N, 1, h, w)
        y = torch.from_numpy(targets(np.asarray(renders.coeffs), np.asarray(renders.centre)))  # (N, 5)
        train_idx, val_idx = split(len(y), config.val_fraction, generator)
        val_frames = np.asarray(renders.frames[val_idx.numpy()])  # (V, H, W), as stored
        dataset_facts = {
            "path": str(renders.path) if dataset is not None else None,
            **{k: renders.manifest[k] for k in ("schema", "generator", "scene_sha256", "samples", "frames", "files")},
            "seed": renders.config.seed,
            "bit_depth": renders.config.bit_depth,
        }
    lab = in_chunks(normalise, lab_frames, "normalise lab frames")
    vae, vae_history = train_vae(lab, config, generator, warm.vae if warm else None)
    head, regressor_history = train_regressor(
        vae.encoder, x, y, train_idx, val_idx, config, generator, warm.head if warm else None
    )
    direct, direct_history = train_direct(
        normalise, x, y, train_idx, val_idx, config, generator, warm.direct if warm else None
    )
    models = {"network": LatentRegressor(normalise, vae.encoder, head).eval(), "direct": direct.eval()}

    results = {"synthetic": {name: (_predict(m, val_frames), y[val_idx].numpy()) for name, m in models.items()}}
    if holdout_video is not None:
        held, _ = read_roi_frames(holdout_video, scene)
        idx, true = oscillation_truth(read_truth(holdout_video), scene)
        results["recording"] = {name: (_predict(m, held[idx]), true) for name, m in models.items()}

    probe = val_frames[:256].astype(config.input_dtype)
    methods = {}
    for name, model in models.items():
        path = export_onnx(model, out / f"{name}.onnx", height, width, config.input_dtype)
        if name == "network":  # its encoder mean, the window model's per-frame input too
            expose_latent(path)
        methods[name] = MethodEntry(
            file=path.name, description=DESCRIPTIONS[name], parity_max_abs=parity(model, path, probe)
        )
    reconstruction = Reconstruction(normalise, vae).eval()
    path = export_onnx(
        reconstruction, out / "autoencoder.onnx", height, width, config.input_dtype, tuple(AUTOENCODER_OUTPUTS)
    )
    autoencoder = MethodEntry(
        file=path.name,
        description=DESCRIPTIONS["autoencoder"],
        parity_max_abs=parity(reconstruction, path, probe, tuple(AUTOENCODER_OUTPUTS)),
    )
    histories = {
        "VAE (negative ELBO)": vae_history,
        "regressor (standardised MSE)": regressor_history,
        "direct CNN (standardised MSE)": direct_history,
    }
    plot_losses(histories, out / "losses.png")
    plot_validation(results, out / "validation.png")
    manifest = Manifest(
        created=datetime.now(UTC).isoformat(timespec="seconds"),
        meniscope=version("meniscope"),
        scene=scene.model_dump(mode="json"),
        scene_sha256=scene.sha256,
        input=InputSpec(
            height=height,
            width=width,
            dtype=config.input_dtype,
            downsample=normalise.factor,
            model_height=x.shape[2],
            model_width=x.shape[3],
        ),
        methods=methods,
        autoencoder=autoencoder,
        training=TrainingSummary(
            dataset=dataset_facts,
            lab_video=lab_facts,
            config=asdict(config),
            seconds=time.perf_counter() - started,
            losses={name: h["val"][-1] for name, h in histories.items()},
        ),
        validation={name: {data: score(*by_method[name]) for data, by_method in results.items()} for name in models},
        files={},
    )
    write_manifest(out, manifest)
    return load_manifest(out, scene)
