"""Read the agent's motion stream from a running dashboard: print each step, optionally save them all.

    python examples/motion_client.py http://127.0.0.1:8998/ --save motion.npz

It opens the dashboard's WebSocket (`/ws`), asks for the motion stream (`{"type": "motion", "enabled": true}`),
and decodes every binary message of kind 4 (an 8-byte header, then one packet of `docs/motion_stream.md`) with
`render.motion_wire.decode`. JSON events are read only to notice the end of the run. `--save` writes the steps
in BEAT2's npz layout (poses (T, 165), trans, expressions, mocap_frame_rate) with `arkit` (T, 52), `steps` and
the ARKit names added: `python -m render.export` reads it.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from pathlib import Path
from urllib.parse import urlsplit, urlunsplit

import aiohttp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing

from render.arkit import ARKIT_INDEX, ARKIT_NAMES  # noqa: E402
from render.motion_wire import MotionPacket, decode  # noqa: E402

BINARY_MOTION = 4  # agent.dashboard.events.BINARY_MOTION
HEADER_BYTES = 8  # agent.dashboard.events.BINARY_HEADER: u8 kind, pad, u16 frame index, u32 step
ENDED = ("ended", "stopped")
AFTER_END_S = 1.0  # how long to wait for late steps once the run has ended


def websocket_url(page_url: str) -> str:
    """http(s)://host:port/ -> ws(s)://host:port/ws"""
    parts = urlsplit(page_url)
    return urlunsplit(("wss" if parts.scheme in ("https", "wss") else "ws", parts.netloc, "/ws", "", ""))


def describe(packet: MotionPacket) -> str:
    """One line per step: its index, the root's height, the jaw and a blink."""
    w = packet.arkit[-1]
    return (
        f"step {packet.step:5d}  frames {packet.n_frames}  root y {packet.trans[-1, 1]:+.3f} m  "
        f"jawOpen {w[ARKIT_INDEX['jawOpen']]:.2f}  eyeBlinkLeft {w[ARKIT_INDEX['eyeBlinkLeft']]:.2f}  "
        f"mouthSmileLeft {w[ARKIT_INDEX['mouthSmileLeft']]:.2f}"
    )


async def read_stream(
    url: str, max_steps: int | None = None, quiet: bool = False, start: bool = False
) -> list[MotionPacket]:
    """The motion packets of the run until it ends, the dashboard closes, or `max_steps` arrived; `start` presses
    the page's Start once subscribed (for a run launched with `--set dashboard.wait_for_start=true`)."""
    packets: list[MotionPacket] = []
    async with aiohttp.ClientSession() as session, session.ws_connect(websocket_url(url), max_msg_size=0) as ws:
        await ws.send_str(json.dumps({"type": "motion", "enabled": True}))
        if start:
            await ws.send_str(json.dumps({"type": "control", "command": "start"}))
        ended = False
        while max_steps is None or len(packets) < max_steps:
            try:  # the last steps travel on another topic than the run's end and may follow it: wait a moment
                msg = await ws.receive(timeout=AFTER_END_S if ended else None)
            except asyncio.TimeoutError:
                break
            if msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.ERROR):
                break
            if msg.type == aiohttp.WSMsgType.BINARY and msg.data[0] == BINARY_MOTION:
                packets.append(decode(memoryview(msg.data)[HEADER_BYTES:]))
                if not quiet:
                    print(describe(packets[-1]), flush=True)
            elif msg.type == aiohttp.WSMsgType.TEXT:
                event = json.loads(msg.data)
                ended = ended or (event.get("type") == "run" and event.get("phase") in ENDED)
    return packets


def save(packets: list[MotionPacket], path: Path) -> None:
    """The steps in step order as one npz (BEAT2's layout plus `arkit`, `arkit_names` and `steps`)."""
    packets = sorted(packets, key=lambda p: p.step)
    poses = np.concatenate([p.poses for p in packets])  # (T, 55, 3)
    np.savez(
        path,
        poses=poses.reshape(len(poses), -1),
        trans=np.concatenate([p.trans for p in packets]),
        expressions=np.concatenate([p.expressions for p in packets]),
        arkit=np.concatenate([p.arkit for p in packets]),
        arkit_names=np.array(ARKIT_NAMES),
        steps=np.array([p.step for p in packets]),
        mocap_frame_rate=np.float32(packets[0].fps),
    )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("url", help="the dashboard's address (printed by launch.py, or <run dir>/dashboard.url)")
    p.add_argument("--save", type=Path, metavar="OUT.npz", help="write the steps here when the stream ends")
    p.add_argument("--steps", type=int, help="stop after this many steps")
    p.add_argument("--quiet", action="store_true", help="do not print each step")
    p.add_argument("--start", action="store_true", help="start a run that waits for a page's Start")
    args = p.parse_args(argv)
    packets = asyncio.run(read_stream(args.url, args.steps, args.quiet, args.start))
    print(f"{len(packets)} steps", file=sys.stderr)
    if args.save and packets:
        save(packets, args.save)
        print(f"wrote {args.save}", file=sys.stderr)
    return 0 if packets else 1


if __name__ == "__main__":
    raise SystemExit(main())
