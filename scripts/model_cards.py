"""Write the model cards of the shipped codecs and gesture LM from a training run's records.

python scripts/model_cards.py WORK SHIP   (scripts/train_default.sh calls it)
"""

import json
import sys
from pathlib import Path

import yaml

W, S = Path(sys.argv[1]), Path(sys.argv[2])
CODEC = yaml.safe_load(Path("ecas/configs/codec/default_small.yaml").read_text())["train"]
DECODER = yaml.safe_load(Path("ecas/configs/codec/default_small_finetune.yaml").read_text())["train"]
LM = yaml.safe_load(Path("ecas/configs/lm/default_small.yaml").read_text())["train"]
times = dict(line.split("\t") for line in (W / "wall_times.tsv").read_text().splitlines())
rows, tuned = [], []
for r in ("upper", "lower", "face"):
    for stage, record in (("", W / f"codec_{r}.json"), (" (decoder fine-tuned)", W / f"decoder_{r}.json")):
        if not record.is_file():
            continue
        last = json.loads(record.read_text())["last"]
        key = "jaw_error_deg" if r == "face" else "mpjpe_mm"
        rows.append(
            f"| {r}{stage} | {last['step']} | {last['train'][key]:.2f} | {last['heldout'][key]:.2f} | "
            f"{last['train']['feature_mse']:.5f} | {last['heldout']['feature_mse']:.5f} |"
        )
        tuned += [r] if stage else []
STEPS = {r: json.loads((W / f"codec_{r}.json").read_text())["last"]["step"] for r in ("upper", "lower", "face")}
size = {r: (S / "codecs" / r / "model.safetensors").stat().st_size / 1e6 for r in ("upper", "lower", "face")}


def run_notes(card: str) -> str:
    """What the training run wrote down for this card ($WORK/notes_<card>.md), e.g. a stage that was resumed."""
    notes = W / f"notes_{card}.md"
    return "\n" + notes.read_text() if notes.is_file() else ""


def generation(mix: Path) -> dict:
    """generation.json of the synthetic sessions that a mixed BEAT2-layout directory of train_default.sh links to."""
    take = next((mix / "smplxflame_25").glob("*_synth_*"))
    return json.loads((take.resolve().parents[1] / "generation.json").read_text())


def data_line(mix: Path) -> str:
    """What a mixed BEAT2-layout directory of train_default.sh holds, from its split file and its sessions'
    generation.json."""
    gen = generation(mix)
    rows = [line.split(",") for line in (mix / "train_test_split.csv").read_text().splitlines()[1:]]
    n_synthetic = sum("_synth_" in take for take, _ in rows)
    held = [take.split("_")[3] for take, split in rows if split == "test"]
    held_out = ", ".join(held) if len(held) <= 3 else f"{held[0]}, {held[1]}, …, {held[-1]}"
    return (
        f"{n_synthetic} synthetic dyadic sessions × {gen['minutes']:g} min (`ecas synthetic "
        f"--seed {gen['seed']}`, default SynthConfig, sessions 1..{n_synthetic}; sessions {held_out} are the "
        "held-out `test` split), plus the real BEAT2 clip `2_scott_0_1_1` (63.5 s, train split). Made by the "
        f"generator with fingerprint `{gen['generator_sha256'][:16]}` "
        "(`gesture.synth.build.generator_fingerprint`, in the data's `generation.json`)."
    )


def codec_origin(region: str) -> Path:
    """The run that trained a region's codec: this one, or the one train_default.sh copied it from
    (CODECS_FROM, recorded in $WORK/codec_origin_<region>)."""
    record = W / f"codec_origin_{region}"
    return Path(record.read_text().strip()) if record.is_file() else W


def codec_data_lines() -> str:
    """Per group of regions trained in the same run, the data that trained them."""
    origins = {r: codec_origin(r) for r in ("upper", "lower", "face")}
    lines = []
    for origin in dict.fromkeys(origins.values()):
        regions = " and ".join(r for r, o in origins.items() if o == origin)
        where = "trained in this run" if origin == W else f"copied unchanged from `{origin}`, trained there"
        lines.append(f"- {regions}: {where} on {data_line(origin / 'codec_data')}")
    return "\n".join(lines)


DECODER_STAGE = (
    "; stage `decoders`: `ecas train-codec --config ecas/configs/codec/default_small_finetune.yaml "
    f"--region <region> --data $WORK/cache --finetune-decoder $WORK/codecs/<region> --out "
    f"$WORK/decoders/<region> --steps <the region's steps>` for {' and '.join(tuned)}"
    if tuned
    else ""
)


def codec_time(region: str) -> str:
    """A region's codec training time, and where it was measured when the codec was copied."""
    where = "" if codec_origin(region) == W else f" in `{codec_origin(region)}`"
    return f"{region} {int(times[f'codec_{region}'])} s{where}"


CODEC_TIMES = (
    f"codec stage (the regions trained here, in parallel on 2 cores) {int(times['codecs'])} s ("
    + ", ".join(codec_time(r) for r in ("upper", "lower", "face"))
    + f"), decoder fine-tuning {int(times.get('decoders', 0))} s"
)
SYNTHETIC_TIME = (
    f"synthetic data {int(times['synthetic'])} s"
    if "synthetic" in times
    else "synthetic data made by an earlier run (SYNTHETIC), not timed here"
)
TERMS = """## Terms
- The synthetic sessions are made by this project's generator (`gesture/synth`, MIT like the rest of the code;
  its voices are espeak-ng's). The generator's calibration (`gesture/synth/calibration.json`: rest posture,
  hand shape, gesture space and the micro-motion fitted by `python -m gesture.eval.synth_fit`) is measured on the
  real BEAT2 clip `2_scott_0_1_1`.
- The real clip `2_scott_0_1_1` (motion and speech) is BEAT2 data (Liu et al., EMAGE, CVPR 2024) under BEAT2's
  licence: research use with attribution. Because it is part of the training data, these weights carry BEAT2's
  terms too; the project's MIT licence covers the code only."""
DECODER_TEXT = (
    f"""Then the decoder half is fine-tuned for {" and ".join(tuned)}, with the encoder and quantizer
frozen (the codes, and so the LM's tokens, do not change): `ecas/configs/codec/default_small_finetune.yaml`, lr
{DECODER["lr"]:g}, batch {DECODER["batch_size"]}, the steps in the table below (`decoder_loss_curve.png`), with the
reference's losses but the FK joint-position MSE weighted {DECODER["joint_position_weight"]:g} (the reference's 10;
`gesture.codec.losses`), so that errors near the root, which move every joint after them, weigh more."""
    if tuned
    else "No decoder fine-tuning (`DECODER_REGIONS` is empty for this ship)."
)
codec_data = codec_data_lines() + "\nCut into 10 s chunks by `python -m gesture.data.build`."
lm_data = "- " + data_line(W / "data")
codec = f"""# The default gesture codecs (upper+hands, lower, face)

Three causal RVQ-VAE codecs (gesture.codec, 2 frames per 80 ms step, 256 codes of dimension 32; n_q 8/8/4),
trained on CPU for the shipped default agent. Load with `gesture.lm.codecs.load_codecs("ecas/checkpoints/codecs")` or
`gesture.codec.checkpoint.load_codec("ecas/checkpoints/codecs/<region>")`; `ecas/configs/default.yaml` points
`gesture.codec_checkpoints` here. Sizes (fp32 safetensors): upper {size["upper"]:.1f} MB, lower {size["lower"]:.1f} MB,
face {size["face"]:.1f} MB.

## Data
{codec_data}

## Config
`ecas/configs/codec/default_small.yaml` (each region's `config.yaml` here is the full dump): latent 128, 64 SEANet
filters, 2/2/1 transformer layers, AdamW lr {CODEC["lr"]:g}, batch {CODEC["batch_size"]} windows of up to
{CODEC["window_frames"]} frames, StepLR ×0.8 every {CODEC["lr_step_every"]} steps; upper {STEPS["upper"]}, lower
{STEPS["lower"]}, face {STEPS["face"]} steps. The FK joint-position MSE weighs
{CODEC["joint_position_weight"]:g} (the reference's 10). The face codec has an expression MSE (weight
{CODEC["expression_mse_weight"]:g}) beside the reference's L1: with L1 alone it reconstructed a face that never blinks.
{DECODER_TEXT}
The synthetic sessions are read as their gesture layer (`gesture_poses`): the motion without the small,
speech-independent micro-motion of the spine, neck, head, collars and wrists, which codecs of this size do not carry
(a linear probe of an upper latent trained on the whole motion explained none of it). The default agent adds that
micro-motion after decoding with its micro-motion layer (`gesture.layers.micro_motion`, `ecas/configs/default.yaml`),
from the same fitted model the generator uses.

## Metrics
Reconstruction (offline encode -> decode with all levels) at the last step; MPJPE in mm over the 55 FK joints with
only the region's joints replaced (zero translation), jaw error in degrees for the face; held-out = the synthetic
test sessions:

| region | steps | train MPJPE mm / jaw ° | held-out MPJPE mm / jaw ° | train feature MSE | held-out feature MSE |
|---|---|---|---|---|---|
{chr(10).join(rows)}

The whole-body codec MPJPE (all three regions reconstructed together) on held-out synthetic sessions is in the
quality report (`ecas evaluate --suite default`). Loss curves: `<region>/loss_curve.png`.

{TERMS}

## Reproduce
`bash scripts/train_default.sh` (stage `codecs`: `ecas train-codec --config
ecas/configs/codec/default_small.yaml --region <region> --data $WORK/cache --out $WORK/codecs/<region>
--steps <the region's steps>`, the regions of `CODEC_REGIONS` in parallel, `nice -n 5`, one thread each{DECODER_STAGE}).

Wall time: {CODEC_TIMES}; {SYNTHETIC_TIME}, chunk cache {int(times["chunk_cache"])} s.
"""
(S / "codecs" / "README.md").write_text(codec + run_notes("codecs"))
meta = json.loads((S / "gesture_lm" / "lm.json").read_text())
losses = json.loads((S / "gesture_lm" / "losses.json").read_text())
first, last = losses[0], losses[-1]
fmt = lambda h: ", ".join(f"{k} {v:.3f}" for k, v in h.items() if k != "epoch")
tok = (W / "lm_data" / "speakers.json").read_text()
lm = f"""# The default gesture LM (local-v1)

The temporal + depth gesture transformer (gesture.lm, 20 levels: upper 0-7, lower 8-15, face 16-19, card 256)
conditioned on the LOCAL dialogue backend: its text vocabulary (8192 hashed words) and its speech tokenizer
(8 codes of 256 per step, `ecas/checkpoints/speech_tokenizer`). `lm.json` records the condition spec
`{json.dumps(meta["condition"])}`; the generator refuses any other backend at start-up. Weights are stored in
bfloat16 ({(S / "gesture_lm" / "lm.safetensors").stat().st_size / 1e6:.1f} MB) and loaded as float32 by
`gesture.lm.checkpoint.load_lm`. Speaker indices: `speakers.json` {tok.strip()} — the synthetic agent is `synth`,
so `gesture.speaker` is its index.

## Data
{lm_data}
Tokenized by `ecas tokenize` (train split only): gesture tokens from the three shipped codecs'
encoders (of the synthetic sessions' gesture layer, `gesture_poses`, as the codecs were trained), the agent
channel's speech codes, a text token at each agent word's first step (the clip's words from the local recogniser),
voice activity per step.

## Config
`ecas/configs/lm/default_small.yaml`: d_model {meta["lm"]["d_model"]}, {meta["lm"]["temporal_layers"]} temporal layers,
{meta["lm"]["depth_layers"]} depth layer(s), gated FFN {meta["lm"]["ffn_hidden"]}, VA head; AdamW lr
{LM["lr"]:g}, batch {LM["batch_size"]} windows of {LM["window_steps"]} steps, {last["epoch"]} epochs (config:
{LM["epochs"]}) of {LM["steps_per_epoch"]} steps, StepLR ×{LM["lr_gamma"]} every {LM["lr_step_epochs"]} epochs, CFG
condition dropout, pad input dropout, dropout {meta["lm"]["dropout"]:g}, InfoNCE weight {LM["infonce_weight"]:g}, VA
loss weight {LM["va_weight"]}.

## Metrics
Training losses, epoch 1: {fmt(first)}; epoch {last["epoch"]}: {fmt(last)} (`losses.json`, `loss_curve.png`).
Generation quality (BeatAlign, L1div, voice-activity accuracy, listening/speaking energy, BEAT2 clip, no-collapse)
is measured by `ecas evaluate --suite default --json`, realism against the real clip by
`ecas realism --json`; see the README.

{TERMS}

## Reproduce
`bash scripts/train_default.sh` (stages `tokenize`: `ecas tokenize --root $WORK/data
--codecs $WORK/codecs --out $WORK/lm_data`; `lm`: `ecas train-lm --config
ecas/configs/lm/default_small.yaml --data $WORK/lm_data --codecs $WORK/codecs --out $WORK/lm`;
`ship` converts the weights to bfloat16).

Wall time on 2 cores: tokenize {int(times["tokenize"])} s, LM training {int(times["lm"])} s.
"""
(S / "gesture_lm" / "README.md").write_text(lm + run_notes("gesture_lm"))
