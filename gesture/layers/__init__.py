"""The runtime layers: objects the generator steps in order on each step's tokens or decoded motion, none of them in
the reference. The contract is in `base` (docs/layers.md shows how to add one), the registry in `registry`, and each
layer is its own module:

- `idle_gate` (`idle`, tokens): while the agent is silent, upper and face tokens from recorded idle slices;
- `alternation_filter`: the decoded torso's and legs' frame-to-frame alternation averaged away;
- `foot_lock`: planted feet held where the decoded contacts planted them;
- `stabilizer`: the decoded arms' slow drift smoothed into holds between strokes;
- `micro_motion`: the micro-motion the codecs' training data leaves out, added back;
- `face`: blinks topped up to a rate and brow twitches smoothed.

`reflex`, `signal` and `fitted` are their shared parts (also used by the synthetic data).
"""

from gesture.layers.base import Layer, LayerEnv, Motion, MotionLayer, StepContext, TokenLayer, Tokens
from gesture.layers.registry import LayerSpec, build_layer, build_layers, known_layers, parse_layers, register

__all__ = [
    "Layer",
    "LayerEnv",
    "LayerSpec",
    "Motion",
    "MotionLayer",
    "StepContext",
    "TokenLayer",
    "Tokens",
    "build_layer",
    "build_layers",
    "known_layers",
    "parse_layers",
    "register",
]
