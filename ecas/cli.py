"""The `ecas` command: `ecas [options]` runs the agent (`ecas.launch`), `ecas COMMAND [options]` runs one of the
project's other commands. Each command's code stays in its own module, which `python -m MODULE` also runs; the
module is imported only when its command runs, so `ecas --help` starts quickly.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence
from importlib import metadata

DISTRIBUTION = "embodied-agent"

# command (as typed after `ecas`) -> (module with a `main(argv)`, what it does)
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("ecas.launch", "run the agent (the same as `ecas` with no command)"),
    "evaluate": ("gesture.eval.evaluate", "gesture metrics of a predicted motion against ground truth"),
    "suite": ("gesture.eval.suite", "quality report of the shipped default agent on held-out sessions"),
    "realism": ("gesture.eval.realism", "realism report: the agent against the real speaker, in one table"),
    "hold-bias": ("gesture.eval.hold_bias", "how often the LM repeats its previous code, against its training tokens"),
    "synth-fit": ("gesture.eval.synth_fit", "fit the synthetic agent's micro-motion to real motion"),
    "synthetic": ("gesture.synth.build", "make synthetic dyadic sessions (training data)"),
    "calibrate": ("gesture.synth.calibration", "recompute the generator's calibration.json from a BEAT2 take"),
    "data-build": ("gesture.data.build", "cut a BEAT2-layout directory into the codecs' chunk cache"),
    "train-codec": ("gesture.codec.train", "train a region codec (or fine-tune its decoder)"),
    "tokenize": ("gesture.lm.tokenize", "tokenize a BEAT2-layout directory for the gesture LM"),
    "train-lm": ("gesture.lm.train", "train the gesture LM"),
    "idle-slices": ("gesture.lm.idle_slices", "cut idle token slices for the idle gate"),
    "train-speech-tokenizer": ("dialogue.train_speech_tokenizer", "train the small causal speech tokenizer"),
    "convert-miburi": ("gesture.release.convert", "convert the official MIBURI release to our checkpoints"),
    "speakers": ("gesture.release.speakers", "list a converted LM's speakers, or resolve --character"),
    "fake-release": ("gesture.release.synthetic", "write a random release in the official MIBURI layout"),
    "play": ("render.play", "render a motion file to MP4 (or one frame to PNG)"),
    "avatar": ("render.avatar", "export the built-in avatar as an SMPL-X model file"),
    "screenshot": ("agent.dashboard.browser", "screenshot a dashboard page with headless Chromium"),
    "bench bus": ("bench.bus", "per-hop latency and throughput of the bus"),
    "bench codec": ("bench.codec", "streaming decode time per step of the three codecs"),
    "bench dialogue": ("bench.dialogue", "the local dialogue backend on replayed real speech"),
    "bench gesture-step": ("bench.gesture_step", "one full gesture step: LM tokens, codec decodes, SMPL-X out"),
    "bench render": ("bench.render", "render speed per frame and offline MP4 throughput"),
    "bench quality": ("bench.quality", "the default agent's quality goals, per sampling seed"),
}


def version() -> str:
    try:
        return metadata.version(DISTRIBUTION)
    except metadata.PackageNotFoundError:  # a checkout that was never installed
        return "not installed"


def commands_help() -> str:
    """The command list for `ecas --help`."""
    width = max(map(len, COMMANDS))
    lines = [f"  ecas {name:<{width}}  {what}" for name, (_, what) in COMMANDS.items()]
    return "commands (each takes --help):\n" + "\n".join(lines)


def find_command(argv: Sequence[str]) -> tuple[str, list[str]] | None:
    """(command, its arguments) when argv starts with a command's words; None for the launcher's own options."""
    for words in (2, 1):
        name = " ".join(argv[:words])
        if len(argv) >= words and name in COMMANDS:
            return name, list(argv[words:])
    return None


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--version"]:
        print(f"ecas ({DISTRIBUTION}) {version()}")
        return 0
    found = find_command(argv)
    if found is None and argv[:1] == ["bench"]:
        benches = ", ".join(name.split()[1] for name in COMMANDS if name.startswith("bench "))
        print(f"usage: ecas bench NAME [options] (NAME: {benches})", file=sys.stderr)
        return 2
    if found is None and argv and not argv[0].startswith("-"):
        print(f"ecas: unknown command {argv[0]!r}\n\n{commands_help()}", file=sys.stderr)
        return 2
    name, args = found or ("run", argv)
    module = importlib.import_module(COMMANDS[name][0])
    return module.main(args) or 0


if __name__ == "__main__":
    sys.exit(main())
