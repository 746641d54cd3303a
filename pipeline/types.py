"""Names for the array and callable types the core passes around.

Arrays are numpy arrays; their shapes and units are in each signature's docstring. A state is
one (n,) joint vector in the robot's joint order [rad].
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
Float32Array = npt.NDArray[np.float32]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

StateValidFn = Callable[[FloatArray], bool]
"""Is this state valid (within bounds, collision free)?"""
MotionValidFn = Callable[[FloatArray, FloatArray], bool]
"""Is the straight joint-space motion between two valid states valid?"""
ClearanceFn = Callable[[FloatArray], float]
"""Distance from a state's robot to the nearest obstacle [m]."""
