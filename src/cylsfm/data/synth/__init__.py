"""Procedural 360-degree street scenes with exact ground truth: the built-in benchmark of cylsfm.

A town is a grid of streets (asphalt with lane markings, sidewalks with paving) and blocks of buildings
(boxes of varied size and height with window grids and brick, plaster or concrete facades), with parked
cars, street lamps and trees, optionally cars driving along the lanes, under a sky at infinity. A camera
rides through it like a cyclist's helmet camera: about one metre per frame with smooth speed changes and
occasional stops, turns at intersections, a little pitch, roll and yaw wobble.

Frames are ray cast directly in the target projection (cylindrical, equirectangular or pinhole), anti-aliased
by supersampling, with the true depth of every pixel (the projection's depth; 0 for sky) and the true
camera-to-world pose of every frame. Everything is a vertical prism (boxes and cylinders standing on the
ground), so each ray only has to be tested against the objects whose horizontal footprint lies in its
azimuth: an azimuth-binned candidate list keeps the cost near linear in the number of pixels.

Textures are evaluated at the world point that a ray hits (periodic noise tiles sampled bilinearly, plus
procedural windows, bricks, paving and markings), so every surface carries photometric detail. Shading is
a sun plus ambient light. A scene is a pure function of its seed: the same seed gives the same town,
route, images and ground truth.

World frame: x east, y down (gravity), z north; the ground is the plane y = 0.

The modules, one job each (lowest first): :mod:`.config` (:class:`SynthConfig`), :mod:`.prisms` (the
objects and their materials), :mod:`.textures`, :mod:`.cars`, :mod:`.ride` (the camera's route),
:mod:`.town` (:class:`StreetScene`), :mod:`.raycast`, :mod:`.shading`, :mod:`.render`
(:func:`render_frame`, :func:`make_camera`), :mod:`.generate` (:func:`generate_dataset`: the dataset
writer and its process pool). :mod:`.room` is a separate tiny analytic scene for the geometry tests.
"""

from .cars import CLEARANCE, MovingCar
from .config import SynthConfig
from .generate import generate_dataset
from .render import make_camera, render_frame
from .room import make_pose, render_room
from .town import StreetScene

__all__ = [
    "CLEARANCE",
    "MovingCar",
    "StreetScene",
    "SynthConfig",
    "generate_dataset",
    "make_camera",
    "make_pose",
    "render_frame",
    "render_room",
]
