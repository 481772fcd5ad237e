"""A codec prepared for fast streaming decode: `inference_codec(codec, "int8") -> GestureCodec`.

The result is an eval-mode, frozen COPY (the given codec is not changed and stays trainable) whose decoder
half computes the same function with fewer ops per step and cheaper weights:

- the quantizer decodes by one gather of precomputed projected code vectors (`project_codebooks`);
- the decoder transformer is a `StepTransformer` (LayerScales folded, no masks while streaming);
- the SEANet decoder convs have weight norm folded once (`pack_convs`);
- every decoder matrix is stored in `dtype`: "float32", "float16", "bfloat16" or "int8" (per-output-row
  symmetric int8 weights, bfloat16 activations), each with the fastest kernel this CPU runs: see
  `gesture.nn.weights`.

Activations, caches and the output stay float32; `StreamingDecoder` runs on the copy unchanged, and so do
`codec.decode` offline and the (untouched, float32) encoder half. The copy is for inference only: its decoder
state-dict keys differ from a GestureCodec's, so save and train the original.
"""

from __future__ import annotations

import copy

from gesture.codec.model import GestureCodec
from gesture.codec.step_seanet import pack_convs
from gesture.codec.step_transformer import StepTransformer
from gesture.nn import StreamingModule
from gesture.nn.weights import WEIGHT_FORMS, check_form

INFERENCE_DTYPES = WEIGHT_FORMS


def inference_codec(codec: GestureCodec, dtype: str = "float32") -> GestureCodec:
    """An eval-mode copy of `codec` prepared for fast streaming decode with `dtype` weights (INFERENCE_DTYPES)."""
    check_form(dtype)
    prepared = copy.deepcopy(codec).float().eval().requires_grad_(False)
    for module in prepared.children():
        if isinstance(module, StreamingModule):
            module.stop_streaming()  # a copy of a streaming codec starts with no stream open
    prepared.quantizer.project_codebooks()
    prepared.transformer_decoder = StepTransformer(prepared.transformer_decoder, dtype)
    pack_convs(prepared.seanet_decoder, dtype)
    return prepared
