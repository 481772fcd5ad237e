"""Every message of the bus, and its wire format. The one place that defines them.

A message travels as ZeroMQ frames `topic | header | buffer...`. The header is msgpack: schema version, kind,
the routing fields (source, session, seq, step, t_origin_ns, t_ns, stamps), the scalar payload fields, and a
descriptor (name, dtype, shape) per array field. Arrays travel as raw buffers, never pickled.
"""

from __future__ import annotations

import dataclasses
import enum
import time
import typing
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol

import msgpack
import numpy as np

from ecas.core.body import NUM_EXPRESSIONS, NUM_JOINTS
from ecas.core.timing import FRAMES_PER_STEP, STEP_SAMPLES

SCHEMA_VERSION = 1
N_GESTURE_TOKENS = 20
N_SPEECH_CODES = 8


class Kind(str, enum.Enum):
    """A message's kind; its value is the message's bus topic (the one place topics are named)."""

    AUDIO_USER = "audio.user"
    MIC_AUDIO = "mic.audio"
    DIALOGUE_STEP = "dialogue.step"
    GESTURE_STEP = "gesture.step"
    RENDER_FRAME = "render.frame"
    METRICS = "metrics"
    LOG = "log"
    CONTROL = "control"


class VadState(str, enum.Enum):
    QUIET = "quiet"
    STARTING = "starting"
    SPEAKING = "speaking"
    STOPPING = "stopping"


class Command(str, enum.Enum):
    HEARTBEAT = "heartbeat"  # detail: {"state": StageState, "drops": int}
    START = "start"  # supervisor → stages: the source may begin
    STOP = "stop"  # supervisor → stages: finish now
    EOS = "eos"  # a stage has published its last data message
    PROGRESS = "progress"  # the sink finished `step` (offline credit window)
    PING = "ping"  # supervisor → stage, detail {"to": stage, "t0": ns}
    PONG = "pong"  # stage → supervisor, detail {"t0", "t1", "t2"} (NTP-style clock offset)


class StageState(str, enum.Enum):
    STARTING = "starting"
    READY = "ready"
    RUNNING = "running"
    DONE = "done"


class DecodeError(ValueError):
    """A frame that is not a valid message of this schema. Receivers log it and skip it."""


def array_field(dtype: str, shape: tuple[int, ...] | None = None) -> Any:
    """A numpy payload field with its expected dtype and shape (None: any shape)."""
    return field(default=None, metadata={"dtype": np.dtype(dtype), "shape": shape})


@dataclass
class Message:
    KIND: ClassVar[Kind]
    source: str = ""
    session: str = ""
    seq: int = 0
    step: int = 0
    t_origin_ns: int = 0
    t_ns: int = field(default_factory=time.monotonic_ns)
    stamps: dict[str, int] = field(default_factory=dict)

    @property
    def topic(self) -> str:
        return self.KIND.value


HEADER_FIELDS = tuple(f.name for f in dataclasses.fields(Message))


@dataclass
class AudioUser(Message):
    KIND: ClassVar[Kind] = Kind.AUDIO_USER
    pcm: np.ndarray = array_field("float32", (STEP_SAMPLES,))  # 24 kHz mono


@dataclass
class MicAudio(Message):
    """A chunk of the browser page's microphone as the page sent it (24 kHz mono, any length), published by the
    dashboard for the io stage (`launch.py --browser-mic`)."""

    KIND: ClassVar[Kind] = Kind.MIC_AUDIO
    pcm: np.ndarray = array_field("int16", None)  # (n,)


@dataclass
class DialogueStep(Message):
    KIND: ClassVar[Kind] = Kind.DIALOGUE_STEP
    agent_pcm: np.ndarray = array_field("float32", (STEP_SAMPLES,))
    user_pcm: np.ndarray = array_field("float32", (STEP_SAMPLES,))
    agent_codes: np.ndarray = array_field("int32", (N_SPEECH_CODES,))  # -1: none
    user_codes: np.ndarray = array_field("int32", (N_SPEECH_CODES,))
    text_token: int = -1  # -1: no text token at this step
    text_piece: str = ""
    user_vad_prob: float = 0.0
    user_vad_state: VadState = VadState.QUIET
    agent_speaking: bool = False
    user_partial: str = ""  # current partial ASR hypothesis
    user_words: str = ""  # words finalised at this step
    agent_interrupted: bool = False  # the agent's utterance was cut at this step


@dataclass
class GestureStep(Message):
    KIND: ClassVar[Kind] = Kind.GESTURE_STEP
    poses: np.ndarray = array_field("float32", (FRAMES_PER_STEP, NUM_JOINTS, 3))  # axis-angle, SMPL-X order
    trans: np.ndarray = array_field("float32", (FRAMES_PER_STEP, 3))
    expressions: np.ndarray = array_field("float32", (FRAMES_PER_STEP, NUM_EXPRESSIONS))
    tokens: np.ndarray = array_field("int32", (N_GESTURE_TOKENS,))
    va_prob: float = float("nan")


@dataclass
class RenderFrame(Message):
    KIND: ClassVar[Kind] = Kind.RENDER_FRAME
    frame_index: int = 0  # 0 or 1 within the step
    width: int = 0
    height: int = 0
    encoding: str = "rgb24"  # "rgb24": image is (H, W, 3) uint8; "jpeg": image is the JPEG bytes
    image: np.ndarray = array_field("uint8")


@dataclass
class Metrics(Message):
    KIND: ClassVar[Kind] = Kind.METRICS
    values: dict[str, float] = field(default_factory=dict)


@dataclass
class Log(Message):
    KIND: ClassVar[Kind] = Kind.LOG
    level: str = "info"
    text: str = ""


@dataclass
class Control(Message):
    KIND: ClassVar[Kind] = Kind.CONTROL
    command: Command = Command.HEARTBEAT
    detail: dict[str, Any] = field(default_factory=dict)


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.KIND.value: cls for cls in (AudioUser, MicAudio, DialogueStep, GestureStep, RenderFrame, Metrics, Log, Control)
}


class Serializer(Protocol):
    def encode(self, msg: Message) -> list[bytes | memoryview]: ...

    def decode(self, frames: Sequence[bytes | memoryview]) -> Message: ...


class MsgpackSerializer:
    """msgpack header + raw array buffers."""

    def encode(self, msg: Message) -> list[bytes | memoryview]:
        header: dict[str, Any] = {"schema": SCHEMA_VERSION, "kind": msg.KIND.value}
        header.update({name: getattr(msg, name) for name in HEADER_FIELDS})
        scalars, arrays, buffers = {}, [], []
        for f in _payload_fields(type(msg)):
            value = getattr(msg, f.name)
            if "dtype" in f.metadata:
                array = _check_array(type(msg), f, value)
                arrays.append([f.name, array.dtype.str, list(array.shape)])
                buffers.append(memoryview(np.ascontiguousarray(array)).cast("B"))
            else:
                scalars[f.name] = value.value if isinstance(value, enum.Enum) else value
        header["fields"] = scalars
        header["arrays"] = arrays
        return [msg.topic.encode(), msgpack.packb(header, use_bin_type=True), *buffers]

    def decode(self, frames: Sequence[bytes | memoryview]) -> Message:
        if len(frames) < 2:
            raise DecodeError(f"expected topic and header frames, got {len(frames)} frame(s)")
        header = _unpack_header(frames[1])
        cls = MESSAGE_TYPES.get(header.get("kind"))
        if cls is None:
            raise DecodeError(f"unknown message kind {header.get('kind')!r}")
        if bytes(frames[0]).decode(errors="replace") != cls.KIND.value:
            raise DecodeError(f"topic {bytes(frames[0])!r} does not match kind {cls.KIND.value!r}")
        kwargs = {name: header[name] for name in HEADER_FIELDS if name in header}
        kwargs.update(_decode_scalars(cls, header.get("fields", {})))
        kwargs.update(_decode_arrays(cls, header.get("arrays", []), frames[2:]))
        try:
            return cls(**kwargs)
        except (TypeError, ValueError) as e:
            raise DecodeError(f"{cls.KIND.value}: {e}") from None


def _payload_fields(cls: type[Message]) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(cls) if f.name not in HEADER_FIELDS]


def _check_array(cls: type[Message], f: dataclasses.Field, value: Any) -> np.ndarray:
    if isinstance(value, (bytes, bytearray, memoryview)):
        value = np.frombuffer(value, np.uint8)
    if not isinstance(value, np.ndarray):
        raise TypeError(f"{cls.__name__}.{f.name}: expected a numpy array, got {type(value).__name__}")
    expected = f.metadata["shape"]
    if value.dtype != f.metadata["dtype"]:
        raise TypeError(f"{cls.__name__}.{f.name}: expected dtype {f.metadata['dtype']}, got {value.dtype}")
    if expected is not None and value.shape != expected:
        raise TypeError(f"{cls.__name__}.{f.name}: expected shape {expected}, got {value.shape}")
    return value


def _unpack_header(frame: bytes | memoryview) -> dict:
    try:
        header = msgpack.unpackb(bytes(frame), raw=False)
    except Exception as e:  # msgpack raises several unrelated types
        raise DecodeError(f"header is not msgpack: {e}") from None
    if not isinstance(header, dict):
        raise DecodeError("header is not a mapping")
    if header.get("schema") != SCHEMA_VERSION:
        raise DecodeError(f"schema {header.get('schema')!r}, this build reads schema {SCHEMA_VERSION}")
    return header


def _decode_scalars(cls: type[Message], scalars: dict) -> dict:
    hints = typing.get_type_hints(cls)
    known = {f.name for f in _payload_fields(cls) if "dtype" not in f.metadata}
    out = {}
    for name, value in scalars.items():
        if name not in known:
            raise DecodeError(f"{cls.KIND.value}: unknown field {name!r}")
        tp = hints[name]
        if isinstance(tp, type) and issubclass(tp, enum.Enum):
            try:
                value = tp(value)
            except ValueError:
                raise DecodeError(f"{cls.KIND.value}.{name}: invalid value {value!r}") from None
        out[name] = value
    return out


def _decode_arrays(cls: type[Message], descriptors: list, buffers: Sequence[bytes | memoryview]) -> dict:
    fields = {f.name: f for f in _payload_fields(cls) if "dtype" in f.metadata}
    if len(descriptors) != len(buffers):
        raise DecodeError(f"{cls.KIND.value}: header lists {len(descriptors)} arrays, got {len(buffers)} buffers")
    out = {}
    for (name, dtype, shape), buffer in zip(descriptors, buffers):
        f = fields.get(name)
        if f is None:
            raise DecodeError(f"{cls.KIND.value}: unknown array field {name!r}")
        dtype, shape = np.dtype(dtype), tuple(shape)
        if dtype != f.metadata["dtype"] or (f.metadata["shape"] is not None and shape != f.metadata["shape"]):
            raise DecodeError(
                f"{cls.KIND.value}.{name}: got {dtype}{shape}, expected {f.metadata['dtype']}"
                f"{f.metadata['shape'] or ''}"
            )
        nbytes = int(np.prod(shape)) * dtype.itemsize
        if len(buffer) != nbytes:
            raise DecodeError(f"{cls.KIND.value}.{name}: buffer has {len(buffer)} bytes, expected {nbytes}")
        out[name] = np.frombuffer(buffer, dtype).reshape(shape)
    missing = sorted(set(fields) - set(out))
    if missing:
        raise DecodeError(f"{cls.KIND.value}: missing array {missing[0]!r}")
    return out
