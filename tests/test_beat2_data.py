"""BEAT2 reading, chunking and the chunk cache, on the real clip and on a tiny BEAT2-layout tree."""

import json
import os

import numpy as np
import pytest
import soundfile as sf
import torch

from ecas.core.config import ConfigError
from ecas.core.errors import DataError
from gesture.body.regions import LOWER_VELOCITY_SLICE
from gesture.body.rotation import axis_angle_to_matrix, yaw_of_matrix
from gesture.data.beat2 import find_takes, read_motion, read_split_csv, read_textgrid_words, read_whisper_words
from gesture.data.build import main as build_main
from gesture.data.cache import build_cache
from gesture.data.chunks import chunk_take
from gesture.data.config import DataConfig, build_data_config
from gesture.data.dataset import Beat2Chunks, collate_chunks
from gesture.data.textgrid import parse_textgrid
from tests.data.beat2_clip import BEAT2_DIR, CLIP_ID, CLIP_NPZ, needs_clip

torch.set_num_threads(1)

LONG_TEXTGRID = """File type = "ooTextFile"
Object class = "TextGrid"

xmin = 0
xmax = 4.0
tiers? <exists>
size = 2
item []:
    item [1]:
        class = "IntervalTier"
        name = "words"
        xmin = 0
        xmax = 4.0
        intervals: size = 4
        intervals [1]:
            xmin = 0
            xmax = 0.5
            text = ""
        intervals [2]:
            xmin = 0.5
            xmax = 1.25
            text = "hello"
        intervals [3]:
            xmin = 1.25
            xmax = 2.5
            text = "say ""hi"" 2"
        intervals [4]:
            xmin = 2.5
            xmax = 4.0
            text = "there"
    item [2]:
        class = "TextTier"
        name = "beats"
        xmin = 0
        xmax = 4.0
        points: size = 1
        points [1]:
            number = 1.5
            mark = "b"
"""

SHORT_TEXTGRID = """File type = "ooTextFile"
Object class = "TextGrid"

0
4.0
<exists>
1
"IntervalTier"
"words"
0
4.0
2
0
1.5
"hello"
1.5
4.0
""
"""


def test_textgrid_long_and_short_formats(tmp_path):
    tiers = parse_textgrid(LONG_TEXTGRID)
    assert [t.name for t in tiers] == ["words", "beats"]
    assert [i.text for i in tiers[0].intervals] == ["", "hello", 'say "hi" 2', "there"]
    assert tiers[0].intervals[2].start_s == 1.25 and tiers[1].intervals[0].start_s == 1.5
    short = parse_textgrid(SHORT_TEXTGRID)
    assert [(i.start_s, i.end_s, i.text) for i in short[0].intervals] == [(0, 1.5, "hello"), (1.5, 4.0, "")]
    path = tmp_path / "a.TextGrid"
    path.write_bytes(LONG_TEXTGRID.encode("utf-16"))  # Praat also writes UTF-16
    assert [w.word for w in read_textgrid_words(path)] == ["hello", 'say "hi" 2', "there"]


def test_textgrid_errors(tmp_path):
    with pytest.raises(DataError, match="not a Praat TextGrid"):
        parse_textgrid('"foo" "bar"')
    with pytest.raises(DataError, match="ends early"):
        parse_textgrid(SHORT_TEXTGRID[:-20])
    with pytest.raises(DataError, match="not found"):
        read_textgrid_words(tmp_path / "missing.TextGrid")


def _write_take(root, take_id, poses, trans, expr, fps, sr=16000, words=None, textgrid=None, motion_dir=None):
    motion_dir = root / (motion_dir or f"smplxflame_{fps}")
    motion_dir.mkdir(parents=True, exist_ok=True)
    np.savez(
        motion_dir / f"{take_id}.npz",
        poses=poses.reshape(len(poses), 165),
        trans=trans,
        expressions=expr,
        betas=np.zeros(300, np.float32),
        mocap_frame_rate=np.int32(fps),
    )
    (root / "wave16k").mkdir(exist_ok=True)
    t = np.arange(int(len(poses) / fps * sr)) / sr
    sf.write(root / "wave16k" / f"{take_id}.wav", (0.3 * np.sin(2 * np.pi * 220 * t) * 32767).astype(np.int16), sr)
    if words is not None:
        (root / "whisper_transcription").mkdir(exist_ok=True)
        doc = {"segments": [{"words": [{"word": w, "start": s, "end": e} for w, s, e in words]}]}
        (root / "whisper_transcription" / f"{take_id}.json").write_text(json.dumps(doc))
    if textgrid is not None:
        (root / "textgrid").mkdir(exist_ok=True)
        (root / "textgrid" / f"{take_id}.TextGrid").write_text(textgrid)


def _motion(t, seed):
    rng = np.random.default_rng(seed)
    poses = np.cumsum(rng.normal(scale=0.01, size=(t, 55, 3)), axis=0).astype(np.float32)
    poses[:, 0] = (0.0, 1.0, 0.0)  # facing 1 rad off +z: the chunker must remove that yaw
    trans = np.cumsum(rng.normal(scale=0.002, size=(t, 3)), axis=0) + (0.5, 1.3, -0.2)
    return poses, trans.astype(np.float32), rng.normal(size=(t, 100)).astype(np.float32)


@pytest.fixture
def beat2_tree(tmp_path):
    """A tiny BEAT2-layout language directory: 2 speakers, 30 and 25 fps takes, json and TextGrid words."""
    root = tmp_path / "beat2"
    _write_take(root, "1_wayne_0_1_1", *_motion(90, 0), fps=30, words=[("hi", 0.2, 0.5), ("you", 1.9, 2.3)])
    _write_take(root, "2_scott_0_2_2", *_motion(100, 1), fps=25, textgrid=SHORT_TEXTGRID, motion_dir="smplxflame_30")
    _write_take(root, "2_scott_0_3_3", *_motion(60, 2), fps=30)
    (root / "train_test_split.csv").write_text(
        "id,type\n1_wayne_0_1_1,train\n2_scott_0_2_2,test\n2_scott_0_3_3,additional\n"
    )
    return root


def test_find_takes_layout(beat2_tree):
    takes = {t.take_id: t for t in find_takes(beat2_tree)}
    assert sorted(takes) == ["1_wayne_0_1_1", "2_scott_0_2_2", "2_scott_0_3_3"]
    assert [takes[k].split for k in sorted(takes)] == ["train", "test", "train"]
    assert [takes[k].speaker for k in sorted(takes)] == ["wayne", "scott", "scott"]
    assert takes["1_wayne_0_1_1"].transcript_path.name == "1_wayne_0_1_1.json"
    assert takes["2_scott_0_2_2"].textgrid_path is not None and takes["2_scott_0_2_2"].transcript_path is None
    assert takes["2_scott_0_3_3"].audio_path.parent.name == "wave16k"


def test_chunks_are_canonical_and_aligned(beat2_tree):
    cfg = DataConfig(chunk_frames=20)
    take = next(t for t in find_takes(beat2_tree) if t.take_id == "1_wayne_0_1_1")
    chunks = chunk_take(take, cfg)
    assert chunks.num_chunks == 3  # 90 frames at 30 fps = 2.97 s -> 75 frames at 25 fps -> 3 x 20
    assert (
        chunks.upper.shape == (3, 20, 258) and chunks.lower.shape == (3, 20, 61) and chunks.face.shape == (3, 20, 106)
    )
    assert chunks.audio.shape == (3, 20 * 16000 // 25)
    np.testing.assert_allclose(chunks.start_s, [0.0, 0.8, 1.6])
    np.testing.assert_allclose(chunks.trans[:, 0], 0, atol=1e-7)
    yaw0 = yaw_of_matrix(axis_angle_to_matrix(chunks.poses[:, 0, 0].astype(np.float64)))
    np.testing.assert_allclose(yaw0, 0, atol=1e-6)
    assert [w.word for w in chunks.words[0]] == ["hi"] and chunks.words[1] == ()
    word, start, end = chunks.words[2][0].word, chunks.words[2][0].start_s, chunks.words[2][0].end_s
    assert word == "you" and start == pytest.approx(0.3) and end == pytest.approx(0.7)
    # audio of chunk 1 is the wav from 0.8 s on
    wav, _ = sf.read(take.audio_path, dtype="float32")
    np.testing.assert_allclose(chunks.audio[1][:1000], wav[12800:13800], atol=1e-6)


def test_cache_build_reuse_and_invalidation(beat2_tree, tmp_path):
    cfg = DataConfig(chunk_frames=20)
    out = tmp_path / "cache"
    first = build_cache(find_takes(beat2_tree), cfg, out)
    assert (first["built"], first["reused"]) == (3, 0)
    again = build_cache(find_takes(beat2_tree), cfg, out)
    assert (again["built"], again["reused"]) == (0, 3)
    wav = beat2_tree / "wave16k" / "2_scott_0_3_3.wav"
    os.utime(wav, ns=(1, 1))  # touched, same content: still reused
    assert build_cache(find_takes(beat2_tree), cfg, out)["built"] == 0
    _write_take(beat2_tree, "2_scott_0_3_3", *_motion(60, 7), fps=30)  # content changed
    changed = build_cache(find_takes(beat2_tree), cfg, out)
    assert (changed["built"], changed["reused"]) == (1, 2)
    assert build_cache(find_takes(beat2_tree), DataConfig(chunk_frames=10), out)["built"] == 3  # options changed

    ds = Beat2Chunks(out, splits=["test"])
    assert len(ds) == 10 and ds.speakers == ["scott"]  # 100 frames at 25 fps (the npz's own rate wins)
    item = ds[0]
    assert item["upper"].shape == (10, 258) and item["audio"].shape == (6400,)
    assert item["speaker"] == "scott" and item["split"] == "test"
    assert [w[0] for w in item["words"]] == ["hello"]
    batch = collate_chunks([ds[0], ds[1]])
    assert batch["lower"].shape == (2, 10, 61) and batch["chunk_index"] == [0, 1]


def test_build_cli(beat2_tree, tmp_path, capsys):
    assert build_main(["--root", str(beat2_tree), "--out", str(tmp_path / "c")]) == 0
    assert "3 takes (3 built, 0 reused)" in capsys.readouterr().out
    assert build_main(["--root", str(tmp_path / "nowhere"), "--out", str(tmp_path / "c")]) == 2
    assert "not a directory" in capsys.readouterr().err


def test_malformed_files_name_the_file(tmp_path):
    bad = tmp_path / "1_a_0_0_0.npz"
    np.savez(bad, poses=np.zeros((5, 165)), trans=np.zeros((5, 3)), mocap_frame_rate=30)
    with pytest.raises(DataError, match=r"1_a_0_0_0.npz: motion file has no 'expressions'"):
        read_motion(bad)
    np.savez(bad, poses=np.zeros((5, 160)), trans=np.zeros((5, 3)), expressions=np.zeros((5, 100)), mocap_frame_rate=30)
    with pytest.raises(DataError, match=r"'poses' must be \(T, 165\)"):
        read_motion(bad)
    np.savez(
        bad,
        poses=np.zeros((5, 165)),
        gesture_poses=np.zeros((4, 165)),
        trans=np.zeros((5, 3)),
        expressions=np.zeros((5, 100)),
        mocap_frame_rate=30,
    )
    assert read_motion(bad).poses.shape == (5, 55, 3)
    with pytest.raises(DataError, match=r"'trans' must be \(4, 3\) to match 'gesture_poses'"):
        read_motion(bad, gesture_layer=True)
    bad.write_text("garbage")
    with pytest.raises(DataError, match="not a readable npz"):
        read_motion(bad)
    js = tmp_path / "w.json"
    js.write_text("{oops")
    with pytest.raises(DataError, match="w.json: not valid JSON"):
        read_whisper_words(js)
    js.write_text(json.dumps({"segments": [{"words": [{"word": "x", "start": 0.1}]}]}))
    with pytest.raises(DataError, match=r"segments\[0\].words\[0\] needs word/start/end"):
        read_whisper_words(js)
    csv = tmp_path / "train_test_split.csv"
    csv.write_text("name,kind\na,train\n")
    with pytest.raises(DataError, match="columns 'id' and 'type'"):
        read_split_csv(csv)
    csv.write_text("id,type\na,holdout\n")
    with pytest.raises(DataError, match="unknown split type 'holdout'"):
        read_split_csv(csv)
    csv.unlink()
    np.savez(tmp_path / "nospeaker.npz", x=1)
    with pytest.raises(DataError, match="no speaker field"):
        find_takes(tmp_path)
    with pytest.raises(DataError, match="no chunk cache"):
        Beat2Chunks(tmp_path / "empty")


def test_config_errors_name_the_option():
    with pytest.raises(ConfigError, match="data.chunk_frames"):
        build_data_config({"chunk_frames": 7})
    with pytest.raises(ConfigError, match="data.chunkframes: unknown option"):
        build_data_config({"chunkframes": 10})


@needs_clip
def test_real_clip_directory(tmp_path):
    takes = find_takes(BEAT2_DIR)
    assert [t.take_id for t in takes] == [CLIP_ID] and takes[0].speaker == "scott"
    motion = read_motion(CLIP_NPZ)
    assert motion.poses.shape == (1906, 55, 3) and motion.fps == 30
    result = build_cache(takes, DataConfig(), tmp_path / "cache")
    assert result["takes"][CLIP_ID]["num_chunks"] == 6  # 63.5 s -> 1588 frames at 25 fps -> 6 x 250
    ds = Beat2Chunks(tmp_path / "cache")
    item = ds[5]
    assert item["start_s"] == 50.0 and item["audio"].shape == (160000,)
    assert item["audio"].abs().max() > 0.01  # real speech in the float32 wav
    speed = item["lower"][:, LOWER_VELOCITY_SLICE].norm(dim=-1)
    assert 0.005 < speed.mean().item() < 0.5  # a standing speaker sways at a few cm/s
