"""Loading the official MIBURI release (docs/reference_facts.md §4, §5) into our runtime.

- `ecas convert-miburi --experiment-dir DIR [--codec-dir DIR] --out OUT`: the converter
  (`gesture.release.convert.convert_release`, `release_gesture_config(out, speaker)`).
- `source`: reading release files (prefix strip, bf16 -> fp32, config.yaml, speaker map, idle slices); `ReleaseError`.
- `codecs`, `glm`: sizes from shapes and config, strict key/shape matching (`keys.match_keys`), checks.
- `speakers`: `speakers.json` beside the LM, `resolve_character(NAME|INDEX)`,
  `resolve_character_for_checkpoint(lm_dir, value)`; CLI `python -m gesture.release.speakers LM_DIR`.
- `synthetic`: random releases in the reference layout at any size (tests, timing).
"""
