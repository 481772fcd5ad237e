"""The runtime layers' fitted parameters (gesture/layers/fitted.json) are the synthetic data's: the data generator's
calibration and constants still produce exactly the stored values, and the layers read them from the file.

After a refit of the data generator, rewrite the file with `python -m tests.test_layer_fits --write`.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from gesture.layers.fitted import FITTED_JSON, face_fit, micro_fit


def _sparse(pattern: np.ndarray) -> dict[str, float]:
    return {str(i): float(v) for i, v in enumerate(pattern) if v != 0}


def fits_from_synth() -> dict:
    """The values the layers use, as the data generator (gesture.synth) defines and fits them."""
    from gesture.synth import agent, face
    from gesture.synth.calibration import MICRO_FAST_HZ, load_calibration
    from gesture.synth.config import LAYERED_MICRO_JOINTS

    noise = load_calibration().micro_motion
    return {
        "micro_motion": {
            "joints": {
                str(j): {"std_rad": [float(x) for x in m.std_rad], "cutoff_hz": m.cutoff_hz, "fast_ratio": m.fast_ratio}
                for j, m in sorted(noise.items())
            },
            "layered_joints": list(LAYERED_MICRO_JOINTS),
            "fast_hz": MICRO_FAST_HZ,
            "listening_scale": agent.MICRO_LISTENING,
            "envelope_gain": agent.MICRO_ENVELOPE_GAIN,
            "envelope_smooth_s": agent.MICRO_ENVELOPE_SMOOTH_S,
            "gate_hz": agent.MICRO_GATE_HZ,
            "gate_log_std": agent.MICRO_GATE_LOG_STD,
            "gate_max": agent.MICRO_GATE_MAX,
            "parts": [list(part) for part in agent.MICRO_PARTS],
            "own_gates": [{"joints": list(joints), "log_std": log_std} for joints, log_std in agent.OWN_GATES],
        },
        "face": {
            "blink_row": _sparse(face.BLINK_ROW),
            "brow_row": _sparse(face.BROW_ROW),
            "brow_psi": _sparse(face.BROW_PSI),
            "blinks_per_minute": face.BLINKS_PER_MINUTE,
            "blink_refractory_s": face.BLINK_REFRACTORY_S,
            "blink_rise_s": list(face.BLINK_RISE_S),
            "blink_hold_s": list(face.BLINK_HOLD_S),
            "blink_fall_s": list(face.BLINK_FALL_S),
        },
    }


def test_the_stored_fits_are_the_data_generators():
    assert json.loads(FITTED_JSON.read_text()) == json.loads(json.dumps(fits_from_synth()))


def test_the_layers_read_the_same_arrays_as_the_data_generator():
    from gesture.synth import agent, face
    from gesture.synth.calibration import load_calibration

    for j, m in load_calibration().micro_motion.items():
        stored = micro_fit().joints[j]
        np.testing.assert_array_equal(stored.std_rad, m.std_rad)
        assert (stored.cutoff_hz, stored.fast_ratio) == (m.cutoff_hz, m.fast_ratio)
    assert micro_fit().own_gates == {j: s for joints, s in agent.OWN_GATES for j in joints}
    for name in ("blink_row", "brow_row", "brow_psi", "blink_psi"):
        np.testing.assert_array_equal(getattr(face_fit(), name), getattr(face, name.upper()))


def test_no_layer_imports_the_data_generator():
    from tests.architecture import import_graph
    from tests.test_architecture import REPO

    graph = import_graph(REPO)
    layers = {m: imported for m, imported in graph.items() if m.startswith("gesture.layers")}
    assert len(layers) >= 8
    assert not {m: sorted(i) for m, i in layers.items() if any(x.startswith("gesture.synth") for x in i)}


def test_the_data_fingerprint_covers_the_layer_files_the_data_generator_imports():
    from gesture.synth.build import SHARED_WITH_LAYERS
    from tests.architecture import import_graph
    from tests.test_architecture import REPO

    graph = import_graph(REPO)
    used = {i for m, imported in graph.items() if m.startswith("gesture.synth") for i in imported}
    shared = {name.split(".")[-1] + ".py" for name in used if name.startswith("gesture.layers.")}
    assert shared and shared <= set(SHARED_WITH_LAYERS)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.test_layer_fits", description=__doc__)
    parser.add_argument("--write", action="store_true", help=f"write {FITTED_JSON.name} from gesture.synth")
    args = parser.parse_args(argv)
    if args.write:
        FITTED_JSON.write_text(json.dumps(fits_from_synth(), indent=1) + "\n")
        print(f"wrote {FITTED_JSON}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
