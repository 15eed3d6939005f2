"""View space of the learned denoisers' normal inputs: the rotation from world space to a camera's view frame."""
from __future__ import annotations

from typing import Any

import numpy as np
import torch

#: Mitsuba's camera frame has +x to the image's left and +z forward; view space here is x right, y up,
#: z towards the viewer (OpenGL convention): view = diag(-1, 1, -1) @ camera.
MITSUBA_CAMERA_TO_VIEW = np.diag([-1.0, 1.0, -1.0])


def world_to_view(to_world: Any) -> torch.Tensor:
    """(3, 3) rotation from world space to view space (x right, y up, z towards the viewer) of a
    Mitsuba camera-to-world matrix ``to_world`` (4 x 4 or 3 x 3, nested lists or array)."""
    rotation = np.asarray(to_world, dtype=np.float64)[:3, :3]
    return torch.from_numpy(MITSUBA_CAMERA_TO_VIEW @ rotation.T).float()
