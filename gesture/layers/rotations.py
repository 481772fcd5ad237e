"""The rotation helpers of `gesture.body.rotation` that the layers use, imported on their first call.

The config's validation imports every layer module (gesture.layers.registry) in every process that reads the
config, and `gesture.body.rotation` loads torch: these wrappers keep torch out of the processes that only check
options (the launcher, the io stage). Results are those of `gesture.body.rotation`, bit for bit.
"""

from __future__ import annotations

import numpy as np


def axis_angle_to_matrix_np(aa: np.ndarray) -> np.ndarray:
    from gesture.body.rotation import axis_angle_to_matrix_np as convert

    return convert(aa)


def matrix_to_axis_angle_np(m: np.ndarray) -> np.ndarray:
    from gesture.body.rotation import matrix_to_axis_angle_np as convert

    return convert(m)


def axis_angle_to_quaternion(aa: np.ndarray) -> np.ndarray:
    from gesture.body.rotation import axis_angle_to_quaternion as convert

    return convert(aa)


def quaternion_to_axis_angle(q: np.ndarray) -> np.ndarray:
    from gesture.body.rotation import quaternion_to_axis_angle as convert

    return convert(q)
