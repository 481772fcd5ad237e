"""The soak's memory curve (tests/test_trust_soak.py writes <report>/memory.json) as a markdown table and a PNG.

python scripts/soak_curve.py RUN/memory.json docs/soak_memory.png   # prints the table for docs/soak.md
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

PROCESSES = ("supervisor", "io", "dialogue", "gesture", "render")
ROWS = 12


def main(memory_json: str, png: str) -> None:
    data = json.loads(Path(memory_json).read_text())
    samples = data["samples"]
    t_min = np.array([s["t_s"] for s in samples]) / 60
    print(f"| wall min | {' | '.join(PROCESSES)} |")
    print("|" + "---:|" * (len(PROCESSES) + 1))
    for i in np.linspace(0, len(samples) - 1, ROWS).astype(int):
        cells = [f"{samples[i][p]:.0f}" if samples[i].get(p) else "-" for p in PROCESSES]
        print(f"| {t_min[i]:.1f} | {' | '.join(cells)} |")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    for p in PROCESSES:
        ax.plot(t_min, [s.get(p) or np.nan for s in samples], label=p)
    ax.set(xlabel="wall time (min)", ylabel="resident memory (MB)", title=f"soak: {data['audio_s']:.0f} s of audio")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=80)


if __name__ == "__main__":
    main(*sys.argv[1:3])
