"""Our avatar in a pipecat pipeline.

    python examples/pipecat_avatar.py --tts-wav SPEECH.wav --mp4 OUT.mp4 --json
        A real pipecat Pipeline: SPEECH.wav arrives as a TTS service's audio frames (in real time, in the chunk sizes
        a streaming TTS sends), passes through the avatar service, and a sink writes its video and audio to OUT.mp4.
        Prints one JSON line: pipecat_version, frames, dropped_frames, av_offset_ms (measured from the written file),
        latency_ms {p50, p95} (a speech frame entering the service -> its video frame leaving it), and more.
    python examples/pipecat_avatar.py [--host localhost --port 7860] [--llm-url URL --llm-model NAME]
        The live bot: open http://localhost:7860/client. pipecat's SmallWebRTC transport and development runner, the
        project's local speech recognition (pocketsphinx) and voice (espeak-ng), any OpenAI-compatible LLM (without
        one, the project's rule-based responder).

Needs the `pipecat` extra: pip install '<checkout>[pipecat]'.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing

import numpy as np  # noqa: E402

from ecas.core.timing import SAMPLE_RATE_HZ  # noqa: E402

DEFAULT_CHUNK_MS = (20, 120)  # a streaming TTS sends chunks of about this size (seeded random sizes)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--tts-wav", type=Path, required=True, help="speak this recording as a TTS service would")
    p.add_argument("--mp4", type=Path, help="with --tts-wav: write the avatar's video and the speech here")
    p.add_argument("--json", action="store_true", help="with --tts-wav: print one JSON line of measurements")
    p.add_argument("--chunk-ms", type=int, nargs=2, default=DEFAULT_CHUNK_MS, metavar=("MIN", "MAX"))
    p.add_argument("--speed", type=float, default=1.0, help="TTS speed: 1 is real time, 4 four times faster")
    p.add_argument("--seconds", type=float, default=None, help="speak only the first SECONDS of the recording")
    p.add_argument("--size", type=int, default=384, help="video frame size (square, even)")
    p.add_argument("--camera", default="upper", choices=("full", "upper", "face"))
    p.add_argument("--config", type=Path, default=None, help="the agent's YAML config (default: the packaged one)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if not args.tts_wav.is_file():
        p.error(f"--tts-wav: no such file: {args.tts_wav}")
    if not 1 <= args.chunk_ms[0] <= args.chunk_ms[1]:
        p.error("--chunk-ms: need 1 <= MIN <= MAX")
    if args.speed <= 0:
        p.error("--speed: must be > 0")
    return args


def avatar_service(args: argparse.Namespace):
    from ecas.pipecat import AvatarService
    from render.config import RenderConfig

    render = RenderConfig(live_size=args.size, camera=args.camera)
    return AvatarService(config=args.config, seed=args.seed, render=render)


# -- offline: a recording as a TTS service's stream ---------------------------------------------------------------


def wav_tts_service(speech: np.ndarray, chunk_ms: tuple[int, int], speed: float, seed: int):
    """A pipecat TTS service whose voice is a recording: each TTSSpeakFrame streams `speech` (24 kHz float32) as
    TTSAudioRawFrames of random sizes in `chunk_ms`, each sent once a real-time TTS (times `speed`) has made it."""
    from pipecat.frames.frames import TTSAudioRawFrame
    from pipecat.services.tts_service import TTSService, TTSSettings

    from ecas.pipecat.audio import mono_to_pcm16

    class WavTTSService(TTSService):
        def __init__(self) -> None:
            super().__init__(
                sample_rate=SAMPLE_RATE_HZ,
                push_start_frame=True,
                push_stop_frames=True,
                settings=TTSSettings(model=None, voice=None, language=None),
            )
            self.rng = np.random.default_rng(seed)

        def can_generate_metrics(self) -> bool:
            return False

        async def run_tts(self, text: str, context_id: str):
            t0, pos = time.monotonic(), 0
            while pos < speech.size:
                n = int(self.rng.integers(chunk_ms[0], chunk_ms[1] + 1)) * SAMPLE_RATE_HZ // 1000
                chunk = speech[pos : pos + n]
                pos += chunk.size
                await asyncio.sleep(max(0.0, t0 + pos / SAMPLE_RATE_HZ / speed - time.monotonic()))
                yield TTSAudioRawFrame(mono_to_pcm16(chunk), SAMPLE_RATE_HZ, 1, context_id=context_id)

    return WavTTSService()


async def run_offline(args: argparse.Namespace) -> dict:
    import pipecat
    from pipecat.frames.frames import EndFrame, TTSSpeakFrame, TTSStoppedFrame
    from pipecat.pipeline.pipeline import Pipeline
    from pipecat.pipeline.worker import PipelineParams, PipelineWorker
    from pipecat.processors.frame_processor import FrameProcessor
    from pipecat.workers.runner import WorkerRunner

    from ecas.core.audio_file import load_audio
    from ecas.pipecat.recording import Mp4Sink, speech_offset_ms, video_seconds

    speech = load_audio(args.tts_wav, SAMPLE_RATE_HZ)
    if args.seconds is not None:
        speech = speech[: int(args.seconds * SAMPLE_RATE_HZ)]
    tts = wav_tts_service(speech, tuple(args.chunk_ms), args.speed, args.seed)
    avatar = avatar_service(args)
    mp4 = args.mp4 or Path("pipecat_avatar.mp4")
    sink = Mp4Sink(mp4, avatar.width, avatar.height)
    spoken = asyncio.Event()

    class EndAfterSpeech(FrameProcessor):  # the bot's turn is over once its TTSStoppedFrame has left the avatar
        async def process_frame(self, frame, direction):
            await super().process_frame(frame, direction)
            if isinstance(frame, TTSStoppedFrame):
                spoken.set()
            await self.push_frame(frame, direction)

    worker = PipelineWorker(Pipeline([tts, avatar, EndAfterSpeech(), sink]), params=PipelineParams())
    t_start = time.monotonic()

    async def speak():
        await worker.queue_frame(TTSSpeakFrame("(the recording)"))
        await spoken.wait()
        await worker.queue_frame(EndFrame())

    runner = WorkerRunner(handle_sigint=False)
    await runner.add_workers(worker)
    await asyncio.gather(runner.run(), speak())
    wall_s = time.monotonic() - t_start
    stats = avatar.stats
    speech_s = speech.size / SAMPLE_RATE_HZ
    speech_frames_s = stats.speech_frames / 25
    return {
        "pipecat_version": pipecat.__version__ if hasattr(pipecat, "__version__") else _version("pipecat-ai"),
        "frames": sink.frames,
        "speech_frames": stats.speech_frames,
        "idle_frames": stats.idle_frames,
        "dropped_frames": sink.missing_frames + stats.dropped_frames + stats.skipped_idle_steps * 2,
        "speech_s": round(speech_s, 3),
        "video_s": round(video_seconds(sink.frames), 3),
        "speech_video_ratio": round(speech_frames_s / speech_s, 4),
        "av_offset_ms": round(speech_offset_ms(mp4, speech, sink.first_speech_frame or 0), 1),
        "latency_ms": {"p50": _round(stats.percentile_ms(50)), "p95": _round(stats.percentile_ms(95))},
        "engine_ms": {
            "p50": _round(stats.percentile_ms(50, "engine_ms")),
            "p95": _round(stats.percentile_ms(95, "engine_ms")),
        },
        "render_ms": {
            "p50": _round(stats.percentile_ms(50, "render_ms")),
            "p95": _round(stats.percentile_ms(95, "render_ms")),
        },
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "chunk_ms": list(args.chunk_ms),
        "speed": args.speed,
        "wall_s": round(wall_s, 2),
        "mp4": str(mp4),
    }


def _round(x: float | None) -> float | None:
    return None if x is None else round(x, 1)


def _version(dist: str) -> str:
    from importlib.metadata import version

    return version(dist)


# -- live: the bot in the browser ---------------------------------------------------------------------------------

LIVE: argparse.Namespace | None = None  # the live options, read before pipecat's runner takes the command line
SYSTEM_PROMPT = "You are a friendly embodied assistant. Answer in one or two short spoken sentences, no markdown."


def live_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description="the live avatar bot (pipecat's development runner)")
    p.add_argument("--size", type=int, default=384)
    p.add_argument("--camera", default="upper", choices=("full", "upper", "face"))
    p.add_argument("--config", type=Path, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--llm-url", default=os.environ.get("OPENAI_BASE_URL"), help="an OpenAI-compatible endpoint")
    p.add_argument("--llm-model", default=os.environ.get("ECAS_LLM_MODEL", "gpt-4o-mini"))
    return p


def live_services(args: argparse.Namespace):
    """(stt, llm, tts): the project's local recognition and voice; an OpenAI-compatible LLM when a URL is given,
    else the project's rule-based responder."""
    from ecas.pipecat.local import LocalSTTService, LocalTTSService, RuleResponderService

    if args.llm_url:
        from pipecat.services.openai.llm import OpenAILLMService

        llm = OpenAILLMService(
            api_key=os.environ.get("OPENAI_API_KEY", "none"),
            base_url=args.llm_url,
            settings=OpenAILLMService.Settings(model=args.llm_model),
        )
    else:
        llm = RuleResponderService(seed=args.seed)
    return LocalSTTService(), llm, LocalTTSService()


async def bot(runner_args) -> None:
    """One browser session (pipecat's runner calls this): SmallWebRTC in and out, the avatar as its video."""
    from pipecat.audio.vad.silero import SileroVADAnalyzer
    from pipecat.frames.frames import TTSSpeakFrame
    from pipecat.pipeline.pipeline import Pipeline
    from pipecat.pipeline.worker import PipelineParams, PipelineWorker
    from pipecat.processors.aggregators.llm_context import LLMContext
    from pipecat.processors.aggregators.llm_response_universal import LLMContextAggregatorPair
    from pipecat.processors.audio.vad_processor import VADProcessor
    from pipecat.transports.base_transport import TransportParams
    from pipecat.transports.smallwebrtc.transport import SmallWebRTCTransport
    from pipecat.workers.runner import WorkerRunner

    args = LIVE or live_parser().parse_args([])
    avatar = avatar_service(args)
    params = TransportParams(
        audio_in_enabled=True,
        audio_out_enabled=True,
        video_out_enabled=True,
        video_out_width=avatar.width,
        video_out_height=avatar.height,
        video_out_framerate=25,
    )
    transport = SmallWebRTCTransport(webrtc_connection=runner_args.webrtc_connection, params=params)
    stt, llm, tts = live_services(args)
    context = LLMContext([{"role": "system", "content": SYSTEM_PROMPT}])
    turns = LLMContextAggregatorPair(context)
    vad = VADProcessor(vad_analyzer=SileroVADAnalyzer())
    pipeline = Pipeline(
        [transport.input(), vad, stt, turns.user(), llm, tts, avatar, transport.output(), turns.assistant()]
    )
    worker = PipelineWorker(pipeline, params=PipelineParams(enable_metrics=False))

    @transport.event_handler("on_client_connected")
    async def on_client_connected(transport, client):
        await worker.queue_frame(TTSSpeakFrame("Hello! I am listening."))

    @transport.event_handler("on_client_disconnected")
    async def on_client_disconnected(transport, client):
        await worker.cancel()

    runner = WorkerRunner(handle_sigint=runner_args.handle_sigint)
    await runner.add_workers(worker)
    await runner.run()


def run_live(argv: list[str]) -> None:
    """pipecat's development runner serves its prebuilt WebRTC page (http://HOST:PORT/client); each browser session
    runs `bot`. The runner reads the command line itself (--host, --port, -t ...), with our options added."""
    global LIVE
    from pipecat.runner.run import main as runner_main

    parser = live_parser()
    LIVE, _ = parser.parse_known_args(argv)
    sys.argv = [sys.argv[0], *argv]
    runner_main(parser)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if "--tts-wav" not in argv:
        run_live(argv)
        return 0
    args = parse_args(argv)
    result = asyncio.run(run_offline(args))
    print(json.dumps(result) if args.json else json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
