"""What a run will render for its policy, said before it starts.

Cameras are most of the cost of evaluating a policy that reads them on a CPU: three 640x480 cameras rendered at
every policy call took a 2-core machine over five minutes for eleven episodes that a camera-less policy runs in
one. So a run says up front which cameras it renders, at which size, how many images that makes at most (every
episode running to its horizon) and roughly how long that takes here (timed on the first plan), and how to ask
for smaller images.

The image size is, in order: the run's `width`/`height` when the user sets them (a policy that resizes its
inputs can be sent smaller images than it declares, and is told so by a warning), else the size the policy
declares in its metadata, else RoboDojo's default 640x480.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Any

from xpolicylab.model import PolicyMetadata

DEFAULT_SIZE = (640, 480)
SMALL_HINT = "width=224 height=224"
TIMED_ROUNDS = 2  # frames of each camera timed (a fraction of a second at 640x480 on a CPU)


def image_size(metadata: PolicyMetadata, width: int | None, height: int | None) -> tuple[int, int, str | None]:
    """(width, height, warning or None) of the images a run renders for `metadata`'s cameras."""
    declared = (metadata.image_width, metadata.image_height)
    if width is None and height is None:
        size = (declared[0] or DEFAULT_SIZE[0], declared[1] or DEFAULT_SIZE[1])
        return size[0], size[1], None
    size = (int(width or declared[0] or DEFAULT_SIZE[0]), int(height or declared[1] or DEFAULT_SIZE[1]))
    warning = None
    if metadata.cameras and declared[0] is not None and declared != size:
        warning = (f"policy {metadata.name} declares {declared[0]}x{declared[1]} images; sending "
                   f"{size[0]}x{size[1]} as width/height ask (the policy must resize them)")
    return size[0], size[1], warning


def images_per_second(plan: Any, cameras: Sequence[str], width: int, height: int) -> float:
    """Camera images per second of MuJoCo's renderer on this machine, timed on one plan's first frame."""
    from dojo.backends.mujoco.render import open_renderer

    model = plan.model()
    data = plan.initial_data(model)
    with open_renderer(model, height, width) as renderer:
        for camera in cameras:  # the first frame of each camera uploads textures: not what the run pays per step
            renderer.update_scene(data, camera=camera)
            renderer.render()
        start = time.perf_counter()
        for _ in range(TIMED_ROUNDS):
            for camera in cameras:
                renderer.update_scene(data, camera=camera)
                renderer.render()
        elapsed = time.perf_counter() - start
    return TIMED_ROUNDS * len(cameras) / max(elapsed, 1e-6)


def budget_message(metadata: PolicyMetadata, cameras: Sequence[str], width: int, height: int,
                   horizons: Sequence[int], rate: float | None) -> str:
    """One line: cameras, size, the most images the episodes still to run can need, and the time they take."""
    calls = sum(math.ceil(h / max(1, metadata.chunk_size)) for h in horizons)
    images = calls * len(cameras)
    line = (f"policy {metadata.name} reads {len(cameras)} camera(s) ({', '.join(cameras)}) at {width}x{height}: "
            f"up to {images:,} images for {len(horizons)} episode(s)")
    if rate:
        line += f", about {_duration(images / rate)} of rendering here ({rate:.0f} images/s measured)"
    if width * height > 224 * 224:
        line += f"; a policy that accepts smaller images can be sent them with {SMALL_HINT}"
    return line


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"
