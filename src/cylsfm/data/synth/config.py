"""The parameters of a generated town and ride."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["SynthConfig"]


@dataclass
class SynthConfig:
    """Parameters of a generated town and ride (all lengths in metres, per frame at ``fps``)."""

    frames: int = 200
    speed: float = 1.0  # mean distance per frame
    speed_variation: float = 0.25  # relative amplitude of the smooth speed changes
    stop_probability: float = 0.15  # chance of a short stop at an intersection
    camera_height: float = 1.75
    jitter_deg: float = 2.5  # amplitude of pitch and roll wobble
    yaw_wobble_deg: float = 2.0
    fps: float = 5.0
    moving_cars: int = 0
    block_size: tuple[float, float] = (45.0, 90.0)
    road_half_width: float = 7.0
    sidewalk_width: float = 3.0
    building_height: tuple[float, float] = (5.0, 40.0)
    texture_filter: float = 1.0  # width, in pixels, of the box filter applied to textures (optical blur)
    supersample: int = 1  # 1: quincunx (5 samples, 2 rays a pixel); n >= 2: n x n rays a pixel
    #: the camera's route: "random" (a random walk: turns at intersections), "block" (once around a
    #: block, ending where it started), "eight" (a figure eight around two blocks: the street between them
    #: twice in the same direction, ending where it started), "back" (along streets, around a block and
    #: the same streets back in the opposite direction), "stairs" (alternating left and right turns: never
    #: a place twice). Routes other than "random" fit the ride's length to the town's streets.
    route: str = "random"
    #: build the town as for a ride of this many frames (0: the ride's own): the same seed then gives the
    #: same town to rides of other lengths and routes
    town_frames: int = 0
    #: every building of the town in one colour and one facade style (streets that look alike)
    alike: bool = False
