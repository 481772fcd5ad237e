"""ecas: a real-time, full-duplex embodied conversational agent in the manner of MIBURI, runnable on a CPU.

`from ecas import Engine, MotionStep, Word` gives the public engine (`gesture.engine`): the agent's voice in, the
avatar's motion out, 80 ms at a time. The names load on first use (PEP 562), so `import ecas.core.timing` stays light.
"""

from __future__ import annotations

_ENGINE_NAMES = ("Engine", "MotionStep", "Word")

__all__ = list(_ENGINE_NAMES)


def __getattr__(name: str):
    if name not in _ENGINE_NAMES:
        raise AttributeError(f"module 'ecas' has no attribute {name!r}")
    from gesture import engine

    value = getattr(engine, name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_ENGINE_NAMES})
