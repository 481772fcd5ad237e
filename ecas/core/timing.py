"""Time constants of the loop. One step is 80 ms: 1920 samples at 24 kHz, one text token, two motion frames."""

SAMPLE_RATE_HZ = 24_000
STEP_MS = 80
STEP_HZ = 1000 / STEP_MS  # 12.5
STEP_S = STEP_MS / 1000  # 0.08
STEP_NS = STEP_MS * 1_000_000
STEP_SAMPLES = SAMPLE_RATE_HZ * STEP_MS // 1000  # 1920
MOTION_FPS = 25
FRAMES_PER_STEP = MOTION_FPS * STEP_MS // 1000  # 2
FRAME_SAMPLES = STEP_SAMPLES // FRAMES_PER_STEP  # 960
