"""Train one region codec.

    ecas train-codec --config ecas/configs/codec/small.yaml --region upper \
        [--data ../shared/data/beat2/2_scott_0_1_1.npz] [--steps N] [--out DIR] [--resume]
        [--finetune-decoder TRAINED_DIR | --init-from TRAINED_DIR]

`--finetune-decoder` starts from a trained codec and trains only its decoder half (transformer_decoder and
seanet_decoder) on the codes of the frozen encoder and quantizer: the codes of every clip stay exactly what they
were, so a language model trained on them stays valid, while the reconstruction from those codes improves.
`--init-from` starts every part from a trained codec of the same sizes (a warm start, e.g. under a new loss).

Runs unchanged under torchrun (DDP: gloo on CPU, nccl on GPU; each rank draws its own batches).
Writes DIR/model.safetensors + config.yaml (loadable by gesture.codec.checkpoint.load_codec),
optimizer.safetensors + trainer_state.json (for --resume), and loss_curve.png. Evaluation (MPJPE in
mm, or the jaw error for the face) runs on the training and held-out data at every checkpoint.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel as DDP
from tqdm import tqdm

from ecas.core.body import REGIONS
from ecas.core.config import ConfigError
from ecas.core.paths import real_clip
from ecas.core.threads import limit_threads
from gesture.body.skeleton import Skeleton
from gesture.codec.build import build_codec
from gesture.codec.checkpoint import MODEL_FILE, load_optimizer, save_codec, save_optimizer
from gesture.codec.config import CodecFileConfig, load_codec_config
from gesture.codec.data import load_motion_splits, sample_batch
from gesture.codec.evaluation import evaluate
from gesture.codec.losses import RegionLoss
from gesture.codec.model import GestureCodec

DEFAULT_DATA = real_clip().with_suffix(".npz")


def commitment_ramp(step: int, ramp_steps: int) -> float:
    """0 at step 0, rising linearly to 1 at `ramp_steps`."""
    return 1.0 if ramp_steps == 0 else min(1.0, step / ramp_steps)


def plot_history(history: dict, path: Path, region: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_loss, ax_eval) = plt.subplots(1, 2, figsize=(10, 4))
    ax_loss.plot(history["step"], history["loss"], lw=0.8)
    ax_loss.set(xlabel="step", ylabel="training loss", yscale="log", title=f"{region} codec")
    metric = "jaw_error_deg" if region == "face" else "mpjpe_mm"
    for split in ("train", "heldout"):
        points = [(e["step"], e[split][metric]) for e in history["eval"] if split in e and metric in e[split]]
        if points:
            ax_eval.plot(*zip(*points), marker="o", label=split)
    ax_eval.set(xlabel="step", ylabel=metric.replace("_", " "), title="reconstruction")
    ax_eval.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


class CodecTrainer:
    """Holds the codec, optimiser, schedule and history of one region's training run."""

    def __init__(
        self,
        config: CodecFileConfig,
        region: str,
        data: Path,
        out: Path,
        skeleton: Skeleton,
        device: torch.device = torch.device("cpu"),
        finetune_from: Path | None = None,
        init_from: Path | None = None,
    ) -> None:
        self.config, self.region, self.out, self.skeleton, self.device = config, region, out, skeleton, device
        train = config.train
        self.rank = dist.get_rank() if dist.is_initialized() else 0
        torch.manual_seed(train.seed)  # same weights on every rank
        self.generator = torch.Generator().manual_seed(train.seed + self.rank)  # different batches per rank
        self.train_data, self.heldout_data = load_motion_splits(data, train.holdout_seconds)
        self.codec: GestureCodec = build_codec(config.codec, region).to(device)
        self.frozen: tuple[torch.nn.Module, ...] = ()
        if init_from is not None:
            self._load_weights(init_from)
        if finetune_from is not None:
            self._load_weights(finetune_from)
            self.frozen = (self.codec.seanet_encoder, self.codec.transformer_encoder, self.codec.quantizer)
            for module in self.frozen:
                module.requires_grad_(False)
        # codebook buffers are kept in sync by the codebooks themselves (gesture.codec.quantizer)
        self.model = DDP(self.codec, broadcast_buffers=False) if dist.is_initialized() else self.codec
        self.loss = RegionLoss(
            region,
            skeleton,
            train.log_speed_weight,
            train.speed_floor_mps,
            train.expression_mse_weight,
            train.joint_position_weight,
        ).to(device)
        self.trained = [p for p in self.codec.parameters() if p.requires_grad]
        self.optimizer = torch.optim.AdamW(self.trained, lr=train.lr, weight_decay=train.weight_decay)
        self.scheduler = torch.optim.lr_scheduler.StepLR(self.optimizer, train.lr_step_every, train.lr_gamma[region])
        self.step = 0
        self.history: dict = {"step": [], "loss": [], "eval": []}

    def _load_weights(self, directory: Path) -> None:
        from safetensors.torch import load_file

        self.codec.load_state_dict(load_file(str(directory / MODEL_FILE), device=str(self.device)), strict=True)

    def resume(self) -> None:
        self._load_weights(self.out)
        state = load_optimizer(self.out, self.optimizer)
        self.step, self.history = state["step"], state["history"]
        self.scheduler.load_state_dict(state["scheduler"])
        self.generator.set_state(torch.tensor(state["generator"], dtype=torch.uint8))  # rank 0's stream
        if self.rank:
            self.generator.manual_seed(train_seed_at(self.config.train.seed + self.rank, self.step))
        torch.manual_seed(train_seed_at(self.config.train.seed, self.step))

    def evaluate(self) -> dict:
        result = {"step": self.step, "train": evaluate(self.codec, self.train_data, self.region, self.skeleton)}
        if self.heldout_data:
            result["heldout"] = evaluate(self.codec, self.heldout_data, self.region, self.skeleton)
        self.history["eval"].append(result)
        return result

    def train_step(self) -> float:
        train = self.config.train
        self.codec.train()
        for module in self.frozen:  # frozen halves keep their codebooks: no EMA, dropout or skipped quantization
            module.eval()
        batch = sample_batch(
            self.train_data, self.region, train.batch_size, train.window_frames, train.random_crop_rate, self.generator
        ).to(self.device)  # (B, L, nfeats)
        out = self.model(batch)
        terms = self.loss(out.reconstruction, batch)
        weight = train.commitment_weight * commitment_ramp(self.step, train.commitment_ramp_steps)
        loss = terms["total"] + weight * out.commitment_loss
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.trained, train.grad_clip)
        self.optimizer.step()
        self.scheduler.step()
        self.step += 1
        value = float(loss.detach())
        self.history["step"].append(self.step)
        self.history["loss"].append(value)
        return value

    def save(self) -> None:
        save_codec(self.out, self.codec, self.config, self.region)
        save_optimizer(
            self.out,
            self.optimizer,
            {
                "step": self.step,
                "history": self.history,
                "scheduler": self.scheduler.state_dict(),
                "generator": self.generator.get_state().tolist(),
            },
        )
        plot_history(self.history, self.out / "loss_curve.png", self.region)


def train_seed_at(seed: int, step: int) -> int:
    return seed * 1_000_003 + step


def _summary(result: dict) -> str:
    parts = []
    for split in ("train", "heldout"):
        if split in result:
            metrics = result[split]
            key = "jaw_error_deg" if "jaw_error_deg" in metrics else "mpjpe_mm"
            parts.append(f"{split} {key} {metrics[key]:.2f} (feature mse {metrics['feature_mse']:.5f})")
    return f"step {result['step']}: " + "; ".join(parts)


def main(argv: list[str] | None = None) -> int:
    limit_threads()
    parser = argparse.ArgumentParser(prog="ecas train-codec", description="Train a gesture region codec.")
    parser.add_argument("--config", required=True, type=Path, help="ecas/configs/codec/*.yaml")
    parser.add_argument("--region", required=True, choices=REGIONS)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="a BEAT2 motion npz or a chunk cache dir")
    parser.add_argument("--steps", type=int, help="total steps (default: train.steps of the config)")
    parser.add_argument("--out", type=Path, help="checkpoint directory (default: runs/codec_<region>)")
    parser.add_argument("--resume", action="store_true", help="continue from the checkpoint in --out")
    parser.add_argument(
        "--finetune-decoder",
        type=Path,
        metavar="TRAINED_DIR",
        help="start from this trained codec and train only its decoder (the codes stay fixed)",
    )
    parser.add_argument(
        "--init-from",
        type=Path,
        metavar="TRAINED_DIR",
        help="start every part from this trained codec (same sizes) and train it all",
    )
    parser.add_argument("--smplx-model", type=Path, help="a real SMPL-X model file for the FK joints")
    parser.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    args = parser.parse_args(argv)
    try:
        config = load_codec_config(args.config)
    except ConfigError as err:
        return _usage_error(str(err))
    if args.steps is not None and args.steps < 1:
        return _usage_error(f"--steps: must be >= 1, got {args.steps}")
    if not args.data.exists():
        return _usage_error(f"--data {args.data}: no such file or directory")
    steps = args.steps or config.train.steps
    out = args.out or Path("runs") / f"codec_{args.region}"
    skeleton = Skeleton.from_smplx_model(args.smplx_model) if args.smplx_model else Skeleton.default()
    if args.resume and not (out / MODEL_FILE).is_file():
        parser.error(f"--resume: no checkpoint in {out}")
    for option, directory in (("--finetune-decoder", args.finetune_decoder), ("--init-from", args.init_from)):
        if directory and not (directory / MODEL_FILE).is_file():
            return _usage_error(f"{option} {directory}: no checkpoint there")
    if args.finetune_decoder and args.init_from:
        return _usage_error("--init-from: not with --finetune-decoder (which already starts from its codec)")
    device = _start_distributed(torch.device(args.device))
    try:
        trainer = CodecTrainer(
            config, args.region, args.data, out, skeleton, device, args.finetune_decoder, args.init_from
        )
        _run(trainer, steps, args.resume)
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()
    if trainer.rank == 0:
        final = trainer.history["eval"][-1]
        print(json.dumps({"region": args.region, "first": trainer.history["eval"][0], "last": final}, indent=1))
    return 0


def _usage_error(message: str) -> int:
    """A user mistake: one line, exit code 2."""
    print(f"error: {message}", file=sys.stderr)
    return 2


def _start_distributed(device: torch.device) -> torch.device:
    """Under torchrun (WORLD_SIZE > 1): join the process group; on GPU, one device per local rank."""
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return device
    dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    if device.type == "cuda":
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
    return device


def _run(trainer: CodecTrainer, steps: int, resume: bool) -> None:
    """Train to `steps`; rank 0 evaluates, checkpoints and reports."""
    lead = trainer.rank == 0
    if resume:
        trainer.resume()
    elif lead:
        print(_summary(trainer.evaluate()), file=sys.stderr)
    every = trainer.config.train.checkpoint_every
    with tqdm(
        total=steps, initial=trainer.step, desc=f"codec {trainer.region}", dynamic_ncols=True, disable=not lead
    ) as bar:
        while trainer.step < steps:
            loss = trainer.train_step()
            bar.update(1)
            bar.set_postfix(loss=f"{loss:.4f}")
            if lead and (trainer.step % every == 0 or trainer.step == steps):
                tqdm.write(_summary(trainer.evaluate()), file=sys.stderr)
                trainer.save()


if __name__ == "__main__":
    raise SystemExit(main())
