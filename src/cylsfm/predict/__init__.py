"""Depth maps for images, image folders and videos with a trained checkpoint (``cylsfm predict``).

Inputs are image files (png, jpg ...), folders (every image directly inside, sorted by name) and videos
(anything PyAV decodes: mp4, mkv, mov, webm ...). For an input named ``NAME`` (its file stem or folder
name; a second input of the same name becomes ``NAME-2``) the outputs are::

    OUT/NAME/FRAME.npy   float32 [H,W] depth, > 0: in the network's (unknown) scale, the same for every
                         frame, or in metres with a camera height (one factor for the whole input)
    OUT/NAME/scale.json  which scale, how it was found, the colour range every picture of NAME shares
                         (cylsfm.predict.scale)
    OUT/NAME/FRAME.png   a picture: the frame as the network sees it above its depth coloured by inverse
                         depth (near = bright), enlarged to at least 1024 pixels wide, with a colour scale
                         (cylsfm.export.colorize.depth_picture)
    OUT/NAME/FRAME_full.npy, FRAME_full.png   with --full-resolution: the depth in the input's own camera
                         and size (0 where the model does not see), and its picture
    OUT/NAME.mp4         videos only: input frame above its coloured depth (h264, or mpeg4 without libx264)
    OUT/predict.json     the run's settings: the same command after an interruption (Ctrl-C, SIGTERM, a
                         full disk) keeps the frames already written and predicts the rest

``FRAME`` is an image's file stem, or a video frame's 6-digit index in the video (counted before ``fps``
subsampling). Every file is written atomically (a temporary file, then ``os.replace``), so an interrupted or
failed run leaves complete files only; frames already written stay.

Cameras (:mod:`cylsfm.model.plan`). Without a camera file, an input must be a full 360-degree
cylindrical panorama of the training aspect ratio; its depth comes back at its own resolution. With a
camera file (``camera.json``, see ``cylsfm camera``): a full cylindrical panorama of the training vertical
field of view is used as it is; any other input (an equirectangular 360-degree image, a cylinder of another
vertical field of view, a partial panorama or a pinhole photograph) is first resampled
(:func:`cylsfm.data.convert.to_cylinder`) into the model's cylinder at the network's input size, and its
depth (and the video preview) is at that size. Inputs that are not full panoramas are taken only when they
cover at least :data:`~cylsfm.model.plan.MIN_COVERAGE` of what the network sees: so a pinhole view
only by a model trained on crops (``cylsfm train --fov``) that it covers.

For a model trained on centred crops (``data.fov < 360``) the depth covers the crop the network sees.

Modules: :mod:`cylsfm.data.inputs` (finding and reading the inputs), :mod:`cylsfm.data.video` (PyAV
decoding and the preview writer), :mod:`cylsfm.model.plan` (what the model takes), :mod:`~cylsfm.predict.run`
(the loop).
"""

from ..data.inputs import IMAGE_FILE_SUFFIXES, InputSource, discover_inputs, read_frames
from ..model.plan import (
    ASPECT_TOLERANCE,
    DEFAULT_VFOV_H,
    MIN_COVERAGE,
    Plan,
    coverage,
    model_camera,
    model_vfov_h,
    plan_input,
)
from .run import PredictSummary, predict
from .scale import RideScale, ride_scale

__all__ = [
    "ASPECT_TOLERANCE",
    "DEFAULT_VFOV_H",
    "IMAGE_FILE_SUFFIXES",
    "MIN_COVERAGE",
    "InputSource",
    "Plan",
    "PredictSummary",
    "RideScale",
    "coverage",
    "discover_inputs",
    "model_camera",
    "model_vfov_h",
    "plan_input",
    "predict",
    "read_frames",
    "ride_scale",
]
