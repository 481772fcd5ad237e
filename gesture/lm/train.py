"""Train the gesture LM: `ecas train-lm --config ecas/configs/lm/small.yaml --data DIR --out DIR`.

Data: a directory in the format of `gesture.lm.data` (npz per recording + spec.json). Losses and schedules follow
docs/reference_facts.md §3 (weighted CE, InfoNCE on Gumbel-softmax latents, voice-activity BCE; warm-up, CFG condition
dropout, pad input dropout, tau annealing) with epoch thresholds from the config. `--codecs DIR` takes the three
trained codecs whose codebooks initialise the gesture tables and define the InfoNCE latents; without it the
model's own random tables stand in (a smoke-test setting). Checkpoints (safetensors + sizes + condition spec) and
`loss_curve.png` go to --out; running again with the same --out resumes. Under `torchrun` (WORLD_SIZE > 1) it trains
with DistributedDataParallel, one process per GPU (gloo on CPU), each rank drawing its own batches; rank 0 writes
the checkpoints. On a GPU the forward runs under bf16 autocast.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import torch

from ecas.core.config import ConfigError, build_dataclass, load_yaml
from ecas.core.threads import limit_threads
from gesture.lm.checkpoint import CheckpointError, load_lm, load_train_state, save_lm, save_train_state
from gesture.lm.config import LMConfig, LMFileConfig, LMTrainConfig
from gesture.lm.data import LMBatch, LMDataset
from gesture.lm.losses import contrastive_loss, level_weights, token_ce, voice_activity_bce
from gesture.lm.model import GestureLM
from gesture.lm.schedule import condition_drop_probability, drop_conditions, gumbel_tau, pad_input_rate, pad_inputs


def level_groups(sizes: LMConfig) -> list[slice]:
    """The levels of each codec: upper, lower, face."""
    upper, lower = sizes.n_upper, sizes.n_upper + sizes.n_lower
    return [slice(0, upper), slice(upper, lower), slice(lower, sizes.n_levels)]


def training_losses(
    model: GestureLM, batch: LMBatch, epoch: float, cfg: LMTrainConfig, generator: torch.Generator, forward=None
) -> dict[str, torch.Tensor]:
    """All loss terms of one batch at (fractional) `epoch`, with the schedules applied. `forward` is the model or
    its DistributedDataParallel wrapper."""
    sizes = model.sizes
    text, audio = drop_conditions(batch.text, batch.audio, condition_drop_probability(epoch, cfg), generator)
    inputs = pad_inputs(batch.tokens, sizes, pad_input_rate(epoch, cfg), generator)
    device = next(model.parameters()).device
    with torch.autocast("cuda", dtype=torch.bfloat16, enabled=device.type == "cuda"):
        out = (forward or model)(inputs.to(device), text.to(device), audio.to(device), batch.speaker.to(device))
    out.logits = out.logits.float()
    out.va_logit = None if out.va_logit is None else out.va_logit.float()
    batch = LMBatch(
        *(t.to(device) for t in (batch.tokens, batch.text, batch.audio, batch.vad, batch.speaker, batch.va_weight))
    )
    weights = level_weights(sizes.n_levels, sizes.face_levels, cfg.face_ce_weight)
    losses = {"ce": token_ce(out.logits, batch.tokens, weights, sizes.pad_token)}
    total = losses["ce"]
    if cfg.infonce_weight > 0:
        codebooks = [model.codebook_vectors(k) for k in range(sizes.n_levels)]
        losses["infonce"] = contrastive_loss(
            out.logits,
            batch.tokens,
            codebooks,
            level_groups(sizes),
            gumbel_tau(epoch, cfg),
            cfg.infonce_segment_steps,
            cfg.infonce_temperature,
            generator,
        )
        total = total + cfg.infonce_weight * losses["infonce"]
    if out.va_logit is not None:
        losses["va"] = voice_activity_bce(out.va_logit, batch.vad, batch.va_weight)
        total = total + cfg.va_weight * losses["va"]
    losses["total"] = total
    return losses


def save_loss_curve(history: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for key in ("total", "ce", "infonce", "va"):
        if history and key in history[0]:
            ax.plot([h["epoch"] for h in history], [h[key] for h in history], label=key)
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def train(
    file_cfg: LMFileConfig,
    data_dir: Path,
    out_dir: Path,
    codecs_dir: Path | None = None,
    epochs: int | None = None,
    progress: bool = True,
) -> list[dict]:
    """Train (or resume) into out_dir; returns the per-epoch loss history."""
    from tqdm import tqdm

    cfg = file_cfg.train
    spec = file_cfg.condition
    epochs = cfg.epochs if epochs is None else epochs
    rank, world, device = _distributed()
    torch.manual_seed(cfg.seed)
    generator = torch.Generator().manual_seed(cfg.seed + rank)
    dataset = LMDataset(data_dir, file_cfg.lm.n_levels, spec)
    resumed = (out_dir / "lm.json").exists()
    model = load_lm(out_dir, spec).train() if resumed else GestureLM(file_cfg.lm, spec)
    if not resumed:
        _init_codebooks(model, codecs_dir)
    model.to(device)
    forward = model
    if world > 1:
        forward = torch.nn.parallel.DistributedDataParallel(  # depth key/value copies 1..18 are never used
            model, device_ids=[device] if device.type == "cuda" else None, find_unused_parameters=True
        )
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    scheduler = torch.optim.lr_scheduler.StepLR(optimizer, cfg.lr_step_epochs, cfg.lr_gamma)
    history: list[dict] = []
    start_epoch = 0
    state = load_train_state(out_dir) if resumed else None
    if state is not None:
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        if rank == 0:
            generator.set_state(state["generator"])
        history = state["losses"]
        start_epoch = len(history)
    for epoch in range(start_epoch, epochs):
        sums: dict[str, float] = {}
        bar = tqdm(
            range(cfg.steps_per_epoch),
            desc=f"epoch {epoch + 1}/{epochs}",
            disable=not progress or rank > 0,
            leave=False,
        )
        for i in bar:
            batch = dataset.sample(cfg.batch_size, cfg.window_steps, generator)
            losses = training_losses(model, batch, epoch + i / cfg.steps_per_epoch, cfg, generator, forward)
            optimizer.zero_grad(set_to_none=True)
            losses["total"].backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            optimizer.step()
            for k, v in losses.items():
                sums[k] = sums.get(k, 0.0) + float(v.detach())
            bar.set_postfix(loss=f"{float(losses['total'].detach()):.3f}")
        scheduler.step()
        history.append({"epoch": epoch + 1, **{k: v / cfg.steps_per_epoch for k, v in sums.items()}})
        if progress and rank == 0:
            tqdm.write(json.dumps(history[-1]))
        if rank == 0 and ((epoch + 1) % cfg.checkpoint_every_epochs == 0 or epoch + 1 == epochs):
            _checkpoint(model, optimizer, scheduler, generator, history, out_dir, epoch + 1, cfg)
    if world > 1:
        torch.distributed.barrier()
        torch.distributed.destroy_process_group()
    return history


def _distributed() -> tuple[int, int, torch.device]:
    """(rank, world size, device); starts the process group under torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    cuda = torch.cuda.is_available()
    device = torch.device(f"cuda:{local_rank}") if cuda else torch.device("cpu")
    if world > 1 and not torch.distributed.is_initialized():
        if cuda:
            torch.cuda.set_device(device)
        torch.distributed.init_process_group("nccl" if cuda else "gloo")
    rank = torch.distributed.get_rank() if world > 1 else 0
    return rank, world, device


def _init_codebooks(model: GestureLM, codecs_dir: Path | None) -> None:
    if codecs_dir is None:  # smoke setting: the model's own random tables define the latents
        model.set_codec_codebooks([emb.weight.detach().clone() for emb in model.temporal_gemb], init_embeddings=False)
        return
    from gesture.lm.codecs import codebook_vectors, load_codecs

    model.set_codec_codebooks(codebook_vectors(load_codecs(codecs_dir)))


def _checkpoint(model, optimizer, scheduler, generator, history, out_dir: Path, epoch: int, cfg: LMTrainConfig) -> None:
    save_lm(model, out_dir, epoch=epoch, step=epoch * cfg.steps_per_epoch)
    save_train_state(out_dir, optimizer, scheduler, generator, history)
    (out_dir / "losses.json").write_text(json.dumps(history, indent=1))
    save_loss_curve(history, out_dir / "loss_curve.png")


def main(argv: list[str] | None = None) -> int:
    limit_threads()
    parser = argparse.ArgumentParser(prog="ecas train-lm", description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, required=True, help="ecas/configs/lm/*.yaml")
    parser.add_argument("--data", type=Path, required=True, help="directory of npz recordings (gesture.lm.data)")
    parser.add_argument("--out", type=Path, required=True, help="checkpoint directory (resumed if it exists)")
    parser.add_argument("--codecs", type=Path, default=None, help="directory of the three trained codecs")
    parser.add_argument("--epochs", type=int, default=None, help="override train.epochs")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    try:
        file_cfg = build_dataclass(LMFileConfig, load_yaml(args.config), str(args.config))
    except ConfigError as err:
        return _usage_error(str(err))
    if args.epochs is not None and args.epochs < 1:
        return _usage_error(f"--epochs: must be >= 1, got {args.epochs}")
    if not args.data.is_dir() or not any(args.data.glob("*.npz")):
        return _usage_error(f"--data {args.data}: not a directory of npz recordings (ecas tokenize)")
    args.out.mkdir(parents=True, exist_ok=True)
    try:
        train(file_cfg, args.data, args.out, args.codecs, args.epochs, progress=not args.no_progress)
    except CheckpointError as err:
        return _usage_error(str(err))
    return 0


def _usage_error(message: str) -> int:
    """A user mistake: one line, exit code 2."""
    print(f"error: {message}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    raise SystemExit(main())
