import msgpack
import numpy as np
import pytest

from ecas.core.messages import (
    AudioUser,
    Command,
    Control,
    DecodeError,
    DialogueStep,
    GestureStep,
    Log,
    Metrics,
    MicAudio,
    MsgpackSerializer,
    RenderFrame,
    VadState,
)

SER = MsgpackSerializer()


def roundtrip(msg):
    return SER.decode([bytes(f) for f in SER.encode(msg)])


def dialogue_step():
    return DialogueStep(
        step=7,
        t_origin_ns=123,
        stamps={"io": 1, "dialogue": 2},
        agent_pcm=np.linspace(-1, 1, 1920, dtype=np.float32),
        user_pcm=np.zeros(1920, np.float32),
        agent_codes=np.arange(8, dtype=np.int32),
        user_codes=-np.ones(8, np.int32),
        text_token=42,
        text_piece="hello",
        user_vad_prob=0.9,
        user_vad_state=VadState.SPEAKING,
        agent_speaking=True,
        user_partial="how are",
        user_words="how",
        agent_interrupted=True,
    )


@pytest.mark.parametrize(
    "msg",
    [
        AudioUser(step=1, pcm=np.ones(1920, np.float32)),
        MicAudio(pcm=np.arange(-700, 700, 3, dtype="<i2")),  # any length, as the page sent it
        dialogue_step(),
        GestureStep(
            poses=np.random.rand(2, 55, 3).astype(np.float32),
            trans=np.zeros((2, 3), np.float32),
            expressions=np.ones((2, 100), np.float32),
            tokens=np.arange(20, dtype=np.int32),
            va_prob=0.25,
        ),
        RenderFrame(frame_index=1, width=3, height=2, image=np.arange(18, dtype=np.uint8).reshape(2, 3, 3)),
        Metrics(values={"fps": 25.0}),
        Log(level="warning", text="careful"),
        Control(command=Command.PONG, detail={"t0": 1, "t1": 2}),
    ],
)
def test_every_message_round_trips(msg):
    out = roundtrip(msg)
    assert type(out) is type(msg)
    for name, value in vars(msg).items():
        got = getattr(out, name)
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(got, value)
            assert got.dtype == value.dtype
        else:
            assert got == value, name


def test_jpeg_bytes_travel_as_a_buffer():
    out = roundtrip(RenderFrame(encoding="jpeg", image=b"\xff\xd8jpeg"))
    assert out.image.tobytes() == b"\xff\xd8jpeg"


def test_arrays_are_never_pickled():
    frames = SER.encode(dialogue_step())
    header = msgpack.unpackb(bytes(frames[1]))
    assert header["arrays"][0] == ["agent_pcm", "<f4", [1920]]
    assert all(b"pickle" not in bytes(f) and not bytes(f).startswith(b"\x80") for f in frames[2:3])


def _tamper(mutate):
    frames = [bytes(f) for f in SER.encode(dialogue_step())]
    header = msgpack.unpackb(frames[1])
    mutate(frames, header)
    frames[1] = msgpack.packb(header)
    return frames


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda f, h: h.update(schema=99), "schema 99"),
        (lambda f, h: h.update(kind="bogus"), "unknown message kind"),
        (lambda f, h: f.__setitem__(2, f[2][:-4]), "buffer has 7676 bytes, expected 7680"),
        (lambda f, h: f.pop(), "header lists 4 arrays, got 3 buffers"),
        (lambda f, h: h["fields"].update(surprise=1), "unknown field 'surprise'"),
        (lambda f, h: h["fields"].update(user_vad_state="shouting"), "invalid value 'shouting'"),
        (lambda f, h: h["arrays"][0].__setitem__(2, [960]), "expected float32(1920,)"),
    ],
)
def test_bad_frames_raise_one_typed_error(mutate, message):
    with pytest.raises(DecodeError, match=message.replace("(", r"\(").replace(")", r"\)")):
        SER.decode(_tamper(mutate))


def test_garbage_header_and_missing_frames():
    with pytest.raises(DecodeError, match="not msgpack"):
        SER.decode([b"audio.user", b"\xc1\xc1"])
    with pytest.raises(DecodeError, match="expected topic and header"):
        SER.decode([b"audio.user"])


def test_encoding_checks_payload_shapes():
    with pytest.raises(TypeError, match=r"AudioUser.pcm: expected shape \(1920,\)"):
        SER.encode(AudioUser(pcm=np.zeros(100, np.float32)))
