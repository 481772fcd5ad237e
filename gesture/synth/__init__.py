"""Synthetic conversations in BEAT2's layout (`python -m gesture.data.synthetic`): scripted turns voiced by
espeak-ng and a procedural agent whose posture, gestures, hands and face follow its speech, calibrated on a real
clip (`calibration.json`)."""
