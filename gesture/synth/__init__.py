"""Synthetic dyadic conversations in BEAT2's layout (`ecas synthetic`, code in `build`): two
espeak-ng voices take turns (`conversation`) while a procedural agent moves its whole body (`agent`), calibrated
on a real clip (`calibration.json`)."""
