"""Convert the official MIBURI release (docs/reference_facts.md §4, §5) into our checkpoints.

    ecas convert-miburi --experiment-dir models/miburi/goodspk --codec-dir models/miburi/codecs \
        --out checkpoints/miburi-release [--character wayne]

Reads the experiment's `config.yaml`, `speaker_id_to_index.json`, `tokens_idle_slices/` and its GLM
safetensors, plus the three codec safetensors (found under `--codec-dir` / `--experiment-dir` and told apart
by their input width, or given with `--upper/--lower/--face`), and writes

    OUT/lm/            lm.safetensors + lm.json (sizes, condition spec), speakers.json
    OUT/codecs/{upper,lower,face}/   model.safetensors + config.yaml
    OUT/idle/          idle_{upper,face}_tokens_slices.npz
    OUT/release.json   sources, sizes, ignored keys, check results

Every source key is loaded or listed as deliberately ignored; a missing or unexpected key or a wrong shape
stops with one error naming the file and the key. Unless `--no-check`, the converter also verifies the
weight-norm folds and that the GLM's frozen codebooks are the codecs', then runs one streaming step of the
converted release through the runtime's generator.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
from safetensors import safe_open

from ecas.core.body import REGIONS
from ecas.core.config import ConfigError
from ecas.core.threads import limit_threads
from ecas.core.timing import STEP_SAMPLES
from gesture.body.regions import REGION_DIMS
from gesture.codec.checkpoint import save_codec
from gesture.codec.config import CodecFileConfig
from gesture.config import GestureConfig
from gesture.lm.checkpoint import save_lm
from gesture.release.codecs import (
    FIRST_CONV,
    assign_regions,
    check_weight_norm,
    codec_codebooks,
    codec_configs,
    convert_codec,
)
from gesture.release.glm import check_codebooks, convert_glm, read_glm_layout
from gesture.release.source import (
    IDLE_FILES,
    ReleaseError,
    checkpoint_keys,
    read_checkpoint,
    read_experiment_config,
    read_idle_slices,
    read_speaker_map,
    strip_prefix,
)
from gesture.release.speakers import resolve_character, write_speaker_map

LM_DIR, CODECS_DIR, IDLE_DIR, REPORT_FILE = "lm", "codecs", "idle", "release.json"
GLM_MARKER = "temporal_classifier.weight"
CHECK_STEPS = 3


def _candidates(directories: list[Path]) -> list[Path]:
    files = {p for d in directories if d.is_dir() for p in d.rglob("*.safetensors")}
    return sorted(files)


def find_glm(experiment_dir: Path) -> Path:
    """The one safetensors file under the experiment directory that holds a GLM."""
    found = [p for p in _candidates([experiment_dir]) if GLM_MARKER in checkpoint_keys(p)]
    if len(found) != 1:
        what = "no GLM checkpoint" if not found else f"{len(found)} GLM checkpoints ({', '.join(map(str, found))})"
        raise ReleaseError(f"{experiment_dir}: {what} (a safetensors file with {GLM_MARKER!r}); pass --glm FILE")
    return found[0]


def _region_of_file(path: Path) -> str | None:
    with safe_open(str(path), framework="pt") as f:
        keys = {strip_prefix(k): k for k in f.keys()}
        if FIRST_CONV not in keys:
            return None
        nfeats = f.get_slice(keys[FIRST_CONV]).get_shape()[1]
    return next((region for region, dim in REGION_DIMS.items() if dim == nfeats), None)


def find_codecs(directories: list[Path], given: dict[str, Path | None]) -> list[Path]:
    """Codec files: the given ones, then one per missing region found under `directories` (by input width)."""
    chosen = {region: Path(path) for region, path in given.items() if path is not None}
    found: dict[str, list[Path]] = {}
    for path in _candidates(directories):
        region = _region_of_file(path)
        if region is not None and region not in chosen:
            found.setdefault(region, []).append(path)
    for region, paths in found.items():
        if len(paths) > 1:
            raise ReleaseError(
                f"{len(paths)} {region} codecs found ({', '.join(map(str, paths))}); pass --{region} FILE"
            )
        chosen[region] = paths[0]
    missing = [r for r in REGIONS if r not in chosen]
    if missing:
        raise ReleaseError(
            f"no {missing[0]} codec checkpoint found under {', '.join(map(str, directories))}; "
            f"pass --codec-dir DIR or --{missing[0]} FILE"
        )
    return [chosen[r] for r in REGIONS]


def convert_release(
    experiment_dir: Path,
    out: Path,
    *,
    codec_dir: Path | None = None,
    glm: Path | None = None,
    codec_files: dict[str, Path | None] | None = None,
    character: str | None = None,
    check: bool = True,
    force: bool = False,
) -> dict:
    """Convert one experiment (see the module docstring); returns the report also written to OUT/release.json."""
    experiment_dir, out = Path(experiment_dir), Path(out)
    config = read_experiment_config(experiment_dir)
    glm_path = Path(glm) if glm is not None else find_glm(experiment_dir)
    codec_paths = find_codecs([Path(codec_dir) if codec_dir is not None else experiment_dir], codec_files or {})
    codec_sources = assign_regions([read_checkpoint(p) for p in codec_paths])
    codec_cfgs = codec_configs(codec_sources, config)
    codecs = {region: convert_codec(codec_sources[region], codec_cfgs[region], region) for region in REGIONS}
    glm_source = read_checkpoint(glm_path)
    levels = {region: codec_cfgs[region].region(region).n_q for region in REGIONS}
    layout = read_glm_layout(glm_source, config, levels)
    _check_codec_card(layout.sizes.card, layout.sizes.code_dim, codec_cfgs, glm_source.path)
    checks = {}
    if check:
        checks["weight_norm_max_rel_error"] = max(check_weight_norm(codecs[r], codec_sources[r]) for r in REGIONS)
        checks["codebook_max_rel_error"] = check_codebooks(glm_source, codec_codebooks(codec_sources))
    model = convert_glm(glm_source, layout)
    speakers = read_speaker_map(experiment_dir, layout.sizes.n_speakers)
    idle = read_idle_slices(experiment_dir, {"upper": levels["upper"], "face": levels["face"]}, layout.sizes.card)
    default_speaker = resolve_character(character, speakers, layout.sizes.n_speakers) if character else None
    report = {
        "sources": {
            "experiment_dir": str(experiment_dir),
            "glm": str(glm_path),
            "codecs": {r: str(codec_sources[r].path) for r in REGIONS},
        },
        "glm": {
            "stored_dtypes": sorted(str(d) for d in glm_source.dtypes),
            "lm": dataclasses.asdict(layout.sizes),
            "condition": layout.spec.to_dict(),
            "ignored_keys": layout.ignored,
            "unused_keys": layout.unused,
        },
        "codecs": {
            r: {
                "n_q": levels[r],
                "layers": codec_cfgs[r].region(r).num_layers,
                "heads": codec_cfgs[r].region(r).num_heads,
                "latent_dim": codec_cfgs[r].latent_dim,
            }
            for r in REGIONS
        },
        "speakers": speakers,
        "default_speaker": default_speaker,
        "idle_steps": {region: int(tokens.shape[2]) for region, tokens in idle.items()},
    }
    staging = _staging_dir(out, force)
    for region in REGIONS:
        save_codec(staging / CODECS_DIR / region, codecs[region], CodecFileConfig(codec=codec_cfgs[region]), region)
    save_lm(model, staging / LM_DIR)
    del model, glm_source
    write_speaker_map(staging / LM_DIR, speakers)
    (staging / IDLE_DIR).mkdir()
    for region, tokens in idle.items():
        np.savez(staging / IDLE_DIR / IDLE_FILES[region], **{"0": tokens})
    if check:
        checks["step_ms"] = run_streaming_check(staging, default_speaker or 0)
    report["checks"] = checks
    (staging / REPORT_FILE).write_text(json.dumps(report, indent=1))
    _publish(staging, out)
    return report


def _check_codec_card(card: int, code_dim: int, cfgs: dict, glm_path: Path) -> None:
    for region, cfg in cfgs.items():
        if (cfg.codebook_size, cfg.codebook_dim) != (card, code_dim):
            raise ReleaseError(
                f"{glm_path}: key 'temporal_gemb.0.weight' has shape {(card, code_dim)}, but the "
                f"{region} codec's codebooks are ({cfg.codebook_size}, {cfg.codebook_dim})"
            )


def _staging_dir(out: Path, force: bool) -> Path:
    if out.exists() and any(out.iterdir()):
        if not force:
            raise ReleaseError(f"{out}: exists and is not empty; pass --force to replace a previous conversion")
        if not (out / REPORT_FILE).is_file():
            raise ReleaseError(f"{out}: not a previous conversion (no {REPORT_FILE}); refusing to replace it")
    staging = out.with_name(out.name + ".partial")
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    return staging


def _publish(staging: Path, out: Path) -> None:
    if out.exists():
        shutil.rmtree(out)
    staging.rename(out)


def release_gesture_config(out: Path, speaker: int, **overrides) -> GestureConfig:
    """The `gesture:` options that run a converted release (what ecas/configs/miburi-release.yaml says)."""
    out = Path(out)
    return GestureConfig(
        lm_checkpoint=out / LM_DIR,
        codec_checkpoints=out / CODECS_DIR,
        speaker=speaker,
        layers=({"idle": {"slices_dir": out / IDLE_DIR}},),
        **overrides,
    )


def run_streaming_check(out: Path, speaker: int) -> float:
    """Load the converted release the way the gesture stage does and run a few streaming steps; returns the
    median step time in ms. Raises ReleaseError on non-finite output."""
    from gesture.process import build_generator

    generator = build_generator(release_gesture_config(out, speaker, dtype="float32", warmup_steps=0), seed=0)
    silence = np.zeros(STEP_SAMPLES, np.float32)
    times = []
    try:
        for step in range(CHECK_STEPS):
            start = time.perf_counter()
            result = generator.step(
                step % generator.spec.text_vocab, np.zeros(generator.spec.n_audio_codebooks), silence
            )
            times.append((time.perf_counter() - start) * 1e3)
            if not (np.isfinite(result.poses).all() and np.isfinite(result.trans).all()):
                raise ReleaseError(f"{out}: the converted release produced non-finite motion at step {step}")
    finally:
        generator.close()
    return float(np.median(times))


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="ecas convert-miburi", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--experiment-dir",
        type=Path,
        required=True,
        help="the release experiment: config.yaml, speaker_id_to_index.json, tokens_idle_slices/, GLM",
    )
    p.add_argument(
        "--codec-dir",
        type=Path,
        help="where the three codec checkpoints are, searched recursively (default: --experiment-dir)",
    )
    p.add_argument("--glm", type=Path, help="the GLM safetensors (default: the one under --experiment-dir)")
    for region in REGIONS:
        p.add_argument(f"--{region}", type=Path, help=f"the {region} codec safetensors (default: found by shape)")
    p.add_argument("--out", type=Path, required=True, help="output directory (e.g. checkpoints/miburi-release)")
    p.add_argument("--character", help="default speaker, NAME or INDEX (recorded and checked; see --set below)")
    p.add_argument("--no-check", action="store_true", help="skip the fold/codebook checks and the streaming step")
    p.add_argument("--force", action="store_true", help="replace a previous conversion in --out")
    return p.parse_args(argv)


def main(argv=None) -> int:
    limit_threads()
    args = parse_args(argv)
    try:
        report = convert_release(
            args.experiment_dir,
            args.out,
            codec_dir=args.codec_dir,
            glm=args.glm,
            codec_files={r: getattr(args, r) for r in REGIONS},
            character=args.character,
            check=not args.no_check,
            force=args.force,
        )
    except (ReleaseError, ConfigError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    _print_summary(args.out, report)
    return 0


def _print_summary(out: Path, report: dict) -> None:
    lm = report["glm"]["lm"]
    print(
        f"converted to {out}/: LM d={lm['d_model']} temporal {lm['temporal_layers']}x{lm['temporal_heads']} heads, "
        f"depth {lm['depth_layers']}x{lm['depth_heads']}, {lm['n_upper']}+{lm['n_lower']}+{lm['n_face']} levels "
        f"of {lm['card']} codes, {lm['n_speakers']} speaker rows; condition {report['glm']['condition']}"
    )
    for key, reason in sorted(set(report["glm"]["ignored_keys"].items())):
        print(f"  ignored {key}: {reason}")
    for pattern, reason in report["glm"]["unused_keys"].items():
        print(f"  unused at inference {pattern}: {reason}")
    for name, value in report["checks"].items():
        print(f"  check {name}: {value:.3g}")
    speaker = report["default_speaker"]
    speakers = ", ".join(f"{n} ({i})" for n, i in sorted(report["speakers"].items(), key=lambda kv: kv[1]))
    print(f"speakers: {speakers}")
    if speaker is not None:
        print(
            "run it with: python launch.py --mic --config ecas/configs/miburi-release.yaml "
            f"--set gesture.speaker={speaker}"
        )


if __name__ == "__main__":
    raise SystemExit(main())
