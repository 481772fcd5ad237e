"""Run the embodied conversational agent: io → dialogue → gesture → render, each in its own process.

ecas --mic                                     talk to it (real time)
ecas --replay talk.wav                         a recording stands in for the microphone
ecas --replay talk.wav --headless --mp4 out.mp4   offline, lossless, as fast as possible
ecas --speak agent.wav                         the agent speaks this recording (co-speech gesture)
ecas --config miburi-release --mic             a packaged config by name (or any YAML file)

`python launch.py` in a checkout and `python -m ecas.launch` are the same command.
"""

from __future__ import annotations

import argparse
import atexit
import json
import logging
import os
import shutil
import socket
import sys
import tempfile
import time
import uuid
from dataclasses import asdict, replace
from pathlib import Path

import yaml

from agent.io.sources import NoAudioDevice, check_input_device
from agent.latency import format_table
from agent.preflight import check_before_start, check_utf8_arguments
from agent.report_lock import ReportLock
from agent.sections import AppConfig, load_app_config
from agent.stage import SUPERVISOR
from agent.supervisor import Supervisor, run_worker
from ecas.core.atomic import write_text_atomic
from ecas.core.audio_file import AudioFileError, load_audio, scan_audio
from ecas.core.bus import stage_address
from ecas.core.component import RunContext
from ecas.core.config import ConfigError, config_path
from ecas.core.paths import DEFAULT_CONFIG
from ecas.core.threads import limit_threads
from ecas.core.timing import SAMPLE_RATE_HZ

EXIT_USAGE = 2


def parse_args(argv=None) -> argparse.Namespace:
    from ecas.cli import commands_help

    p = argparse.ArgumentParser(
        prog="ecas",
        description=__doc__,
        epilog=commands_help(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    source = p.add_mutually_exclusive_group()
    source.add_argument("--mic", action="store_true", help="listen to the microphone (real time)")
    source.add_argument("--replay", metavar="FILE", help="replay a recording as the user's voice")
    source.add_argument(
        "--browser-mic", action="store_true", help="the dashboard page's microphone is the user's voice (real time)"
    )
    p.add_argument("--speak", metavar="FILE", help="the agent speaks this recording (playback backend)")
    p.add_argument("--headless", action="store_true", help="no dashboard and no speaker")
    p.add_argument(
        "--host", metavar="ADDR", help="serve the dashboard on this address (default 127.0.0.1: this machine only)"
    )
    p.add_argument("--mp4", metavar="OUT", help="write the rendered conversation to this MP4")
    p.add_argument(
        "--avatar", metavar="FILE", help="draw this VRM or Mixamo-rigged GLB in the page (sets render.mode=browser)"
    )
    p.add_argument("--fast", action="store_true", help="as fast as possible and lossless (offline)")
    p.add_argument("--seed", type=int, help="random seed (offline runs are deterministic with it)")
    p.add_argument(
        "--character",
        metavar="NAME|INDEX",
        help="the speaker the gesture model imitates (a name from the checkpoint's speaker map, or a row)",
    )
    p.add_argument("--report", metavar="DIR", help="report directory (default: a new runs/<time>-<suffix>/)")
    p.add_argument(
        "--worker",
        action="store_true",
        help="only start this host's stages (run.spawn); another host's ecas supervises",
    )
    p.add_argument(
        "--config",
        type=_config_arg,
        default=DEFAULT_CONFIG,
        metavar="FILE|NAME",
        help="a YAML config, or a packaged one by name: default, miburi-release (default: the packaged default)",
    )
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override one option, e.g. --set render.size=384 (repeatable)",
    )
    args = p.parse_args(argv)
    if args.browser_mic and args.headless:
        p.error("--browser-mic needs the dashboard: drop --headless")
    return args


def _config_arg(text: str) -> Path:
    try:
        return config_path(text)
    except ConfigError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix(f"--config {text}: ")) from None


def mode_overrides(args: argparse.Namespace, speak_duration_s: float | None) -> list[str]:
    """Translate the mode flags into config overrides (applied before --set, so --set wins)."""
    out = []
    if args.mic:
        out += ["io.source=mic"]
    elif args.replay:
        out += ["io.source=replay", f"io.replay_path={yaml.safe_dump(args.replay).strip()}"]
    elif args.browser_mic:
        out += ["io.source=silence", "run.components.io=agent.dashboard.mic:browser_io", "dashboard.browser_mic=true"]
    elif args.speak:
        out += ["io.source=silence", f"io.silence_s={speak_duration_s + 2.0:.2f}"]
    if args.speak:
        out += ["dialogue.backend=playback", f"dialogue.playback.speak={yaml.safe_dump(args.speak).strip()}"]
    if args.mp4:
        out += [f"render.mp4_path={yaml.safe_dump(args.mp4).strip()}"]
    if args.headless:
        out += ["dashboard.enabled=false", "io.speaker=false"]
    if args.host:
        out += [f"dashboard.host={yaml.safe_dump(args.host).strip()}"]
    if args.avatar:
        out += [f"render.avatar={yaml.safe_dump(args.avatar).strip()}", "render.mode=browser"]
    offline = args.fast or (args.headless and not args.mic)
    out += ["run.live=false" if offline else "run.live=true"]
    if args.seed is not None:
        out += [f"run.seed={args.seed}"]
    if args.report:
        out += [f"run.report_dir={yaml.safe_dump(args.report).strip()}"]
    return out


def with_character(app: AppConfig, character: str) -> AppConfig:
    """Resolve --character against the LM checkpoint's speaker map."""
    from gesture.release.speakers import resolve_character_for_checkpoint

    if app.gesture.lm_checkpoint is None:
        raise ConfigError("--character: gesture.lm_checkpoint is not set")
    speaker = resolve_character_for_checkpoint(Path(app.gesture.lm_checkpoint), character)
    return replace(app, gesture=replace(app.gesture, speaker=speaker))


def with_dialogue_spec(app: AppConfig) -> AppConfig:
    """Tell the gesture stage what the dialogue backend emits, so a mismatched LM fails at start-up."""
    if app.gesture.dialogue_spec is not None or "dialogue" in app.run.components:
        return app
    from dialogue.backend import condition_spec

    return replace(app, gesture=replace(app.gesture, dialogue_spec=condition_spec(app.dialogue)))


def without_relaying_renderer(app: AppConfig) -> AppConfig:
    """render.mode browser without an MP4: the page draws the avatar from the gesture stage's motion, so a render
    stage would draw nothing and only relay messages (about 0.09 of a core); the run leaves it out."""
    if app.render.mode != "browser" or app.render.mp4_path or "render" in app.run.components:
        return app
    return replace(app, run=replace(app.run, stages=tuple(s for s in app.run.stages if s != "render")))


def check_inputs(app: AppConfig) -> None:
    """Fail before any process starts, with one line, on a bad recording or a missing microphone."""
    if "io" not in app.run.local_stages:
        return
    if app.io.source == "replay":
        if not app.io.replay_path:
            raise ConfigError("io.replay_path: no recording to replay (pass --replay FILE or --mic)")
        scan_audio(app.io.replay_path)  # decoded once in constant memory; the io stage streams it again
    elif app.io.source == "mic":
        check_input_device(app.io.input_device)


def check_report_dir(app: AppConfig) -> None:
    if app.run.report_dir and Path(app.run.report_dir).exists() and not Path(app.run.report_dir).is_dir():
        raise ConfigError(f"--report {app.run.report_dir}: exists and is not a directory; give a directory")


def check_mp4_target(app: AppConfig) -> None:
    """The MP4's directory must take a file now, not after every stage has started."""
    if "render" not in app.run.local_stages or not app.render.mp4_path:
        return
    path = Path(app.render.mp4_path)
    if path.is_dir():
        raise ConfigError(f"--mp4 {path}: is a directory; give a file name")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.probe-"):
            pass
    except OSError as e:
        raise ConfigError(f"--mp4 {path}: cannot write there ({e.strerror or e})") from None


def check_checkpoints(app: AppConfig) -> None:
    """The shipped gesture stage needs its checkpoints: say so now, not from inside a started stage."""
    if "gesture" not in app.run.local_stages or "gesture" in app.run.components:
        return
    for key, what in (
        ("lm_checkpoint", "a directory written by ecas train-lm"),
        ("codec_checkpoints", "a directory with the upper/, lower/ and face/ codecs"),
    ):
        path = getattr(app.gesture, key)
        if path is None:
            raise ConfigError(f"gesture.{key}: required ({what}); the config sets none")
        if not Path(path).is_dir():
            raise ConfigError(f"gesture.{key}: {path} is not a directory ({what})")


def with_free_tcp_ports(app: AppConfig) -> AppConfig:
    """`bus.base_port: 0`: every endpoint this run binds takes a port that is free now (an explicit
    `bus.endpoints.<name>` is kept), so two tcp runs on one host never collide."""
    if app.bus.transport != "tcp" or app.bus.base_port != 0:
        return app
    names = [n for n in (*app.run.stages, SUPERVISOR, "dashboard") if n not in app.bus.endpoints]
    probes = [socket.socket(socket.AF_INET6 if ":" in app.bus.host else socket.AF_INET) for _ in names]
    try:
        for probe in probes:
            probe.bind((app.bus.host, 0))
        endpoints = {name: f"tcp://{app.bus.host}:{probe.getsockname()[1]}" for name, probe in zip(names, probes)}
    except OSError as e:
        raise ConfigError(f"bus.host: cannot listen on {app.bus.host} ({e.strerror or e})") from None
    finally:
        for probe in probes:
            probe.close()
    return replace(app, bus=replace(app.bus, endpoints={**endpoints, **app.bus.endpoints}))


def check_ports(app: AppConfig, worker: bool) -> None:
    """Every tcp port this host will listen on must be free: one line naming the port and the option."""
    bindings = [s for s in app.run.local_stages]
    if not worker:
        bindings += [SUPERVISOR] + (["dashboard"] if app.dashboard.enabled else [])
    for stage in bindings:
        address = stage_address(stage, app.bus, Path(tempfile.gettempdir()))
        if not address.startswith("tcp://"):
            continue
        host, _, port = address[len("tcp://") :].rpartition(":")
        option = f"bus.endpoints.{stage}" if stage in app.bus.endpoints else "bus.base_port"
        if not _port_free("" if host == "*" else host.strip("[]"), int(port)):
            raise ConfigError(
                f"{option}: tcp port {port} on {host} ({stage}) is in use, perhaps by another run; set another {option}"
            )
    if app.dashboard.enabled and not worker and app.dashboard.port:
        host, port = app.dashboard.host, app.dashboard.port
        if not _port_free(host, port):
            raise ConfigError(
                f"dashboard.port: {host}:{port} is in use, perhaps by another run's dashboard; "
                f"set another dashboard.port (0 takes any free port)"
            )


def _port_free(host: str, port: int) -> bool:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as ZeroMQ and aiohttp listen
        try:
            probe.bind((host, port))
        except OSError:
            return False
    return True


def main(argv=None, exit_when_done: bool = True) -> int:
    """The launcher. After a run (not after a usage error) it ends the process itself (`exit_fast`), unless
    `exit_when_done` is False; otherwise it returns the exit code: 0, 1 (a stage failed), 2 (usage), 130."""
    limit_threads()
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    try:
        check_utf8_arguments(sys.argv[1:] if argv is None else argv)
        speak_s = len(load_audio(args.speak, SAMPLE_RATE_HZ)) / SAMPLE_RATE_HZ if args.speak else None
        app = load_app_config(args.config, [*mode_overrides(args, speak_s), *args.overrides])
        check_report_dir(app)
        if args.character is not None:
            app = with_character(app, args.character)
        app = without_relaying_renderer(with_dialogue_spec(app))
        check_inputs(app)
        check_checkpoints(app)
        check_before_start(app)
        check_mp4_target(app)
        app = with_free_tcp_ports(app)
        check_ports(app, args.worker)
    except (ConfigError, AudioFileError, NoAudioDevice) as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as e:  # e.g. no usable temporary directory on a full disk
        print(f"error: {' '.join(str(e).split())}", file=sys.stderr)
        return EXIT_USAGE
    try:
        run_dir, created = open_report_dir(app)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_USAGE
    lock = ReportLock(run_dir)
    try:
        lock.acquire()
        write_text_atomic(
            run_dir / "config.yaml", yaml.safe_dump(json.loads(json.dumps(asdict(app), default=str)), sort_keys=False)
        )
    except (ConfigError, OSError) as e:
        lock.release()
        if created and isinstance(e, OSError):
            shutil.rmtree(run_dir, ignore_errors=True)
        what = e if isinstance(e, ConfigError) else f"--report {run_dir}: cannot write there ({e.strerror or e})"
        print(f"error: {what}", file=sys.stderr)
        return EXIT_USAGE
    try:
        code = run(app, args, run_dir)
    finally:
        lock.release()
    if exit_when_done:
        exit_fast(code)
    return code


def exit_fast(code: int) -> None:
    """End the launcher once its run is over and its report written: the atexit handlers, then `os._exit`.

    What that skips is the interpreter's teardown of its modules, 0.5-1 s with matplotlib and aiohttp loaded on a
    loaded 2-core machine, all of it after the report line and before the shell's prompt came back after Ctrl-C.
    """
    atexit._run_exitfuncs()  # logging's flush and multiprocessing's clean-up, as at a normal exit
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    os._exit(code)


def open_report_dir(app: AppConfig) -> tuple[Path, bool]:
    """The run's report directory, and whether this run created it; ConfigError (one line) when it cannot be."""
    existed = bool(app.run.report_dir) and Path(app.run.report_dir).is_dir()
    try:
        return app.run.make_report_dir(time.strftime("%Y%m%d-%H%M%S")), not existed
    except OSError as e:
        raise ConfigError(f"--report {app.run.report_dir or 'runs/'}: cannot create it ({e.strerror or e})") from None


def run(app: AppConfig, args: argparse.Namespace, run_dir: Path) -> int:
    run_ctx = RunContext(run_dir=run_dir.resolve(), live=app.run.live, seed=app.run.seed, session=uuid.uuid4().hex[:12])
    if args.worker:
        return run_worker(app, run_ctx)
    supervisor = Supervisor(app, run_ctx)
    code = supervisor.run()
    try:
        summary = supervisor.latency.write(
            run_dir,
            supervisor.counters(),
            {s: asdict(e) for s, e in supervisor.clock.estimates().items()},
            supervisor.stream_timing(),
            live=app.run.live,
        )
    except OSError as e:
        print(f"error: cannot write the latency report in {run_dir} ({e.strerror or e})", file=sys.stderr)
        return code or 1
    print(format_table(summary))
    print(f"report: {run_dir}/ (latency.json, latency.png, transcript.json, <stage>.log)")
    return code


if __name__ == "__main__":
    sys.exit(main())
