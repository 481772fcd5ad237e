"""The three causal RVQ-VAE gesture codecs (upper+hands 258, lower 61, face 106 features at 25 fps).

- `config.CodecConfig` / `load_codec_config(path)`: sizes (ecas/configs/codec/reference.yaml, small.yaml).
- `build.build_codec(config, region) -> GestureCodec`; `count_parameters`.
- `model.GestureCodec`: `encode(x (B,T,F)) -> codes (B,K,T/2)`, `decode(codes) -> (B,T,F)`, `forward -> CodecOutput`.
- `streaming.StreamingDecoder(codec).step(codes (B,K,1)) -> (B,2,F)`; `StreamingEncoder(codec).step(frames (B,2,F))`.
- `inference.inference_codec(codec, "int8") -> GestureCodec`: an eval-mode copy for fast streaming decode.
- `losses.RegionLoss(region, skeleton)`; `checkpoint.load_codec(dir)` / `save_codec`.
Training: `ecas train-codec`; benchmark: `python -m bench.codec --json`.
"""
