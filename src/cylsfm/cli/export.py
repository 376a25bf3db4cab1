"""``cylsfm export``: the depth network as ONNX; a panorama's depth as a mesh or point cloud, as
omni-directional stereo for VR, and as a web page to look around in."""

from __future__ import annotations

import argparse

from .base import add_amp_argument, command
from .odometry import add_ride_options, ride_settings


def _depth_source(p: argparse.ArgumentParser) -> None:
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="predict the depth with this checkpoint file or run directory")
    src.add_argument("--depth", help="the depth as a .npy file (cylindrical depth in metres, 0 unknown)")
    p.add_argument(
        "--camera",
        help="the panorama's camera.json. Default: its dataset sequence's camera.json when the panorama is "
        "a dataset frame (SEQ/images/X.png); else, with --checkpoint, as 'cylsfm predict' decides (a 2:1 "
        "frame is taken as equirectangular, one of the model's aspect as its full cylinder); with --depth, a "
        "full 360-degree cylinder spanning +-45 degrees of elevation (--depth needs a full cylindrical camera)",
    )
    p.add_argument(
        "--camera-height",
        type=float,
        metavar="METRES",
        help="metric scale: the camera's height above a level ground (fitted below the horizon)",
    )
    m = p.add_mutually_exclusive_group()
    m.add_argument(
        "--mask",
        metavar="IMAGE",
        help="white where the panorama sees the scene, black on the camera's own mount or helmet (same "
        "aspect ratio): no geometry from it. Default: a dataset frame's sequence mask.png",
    )
    m.add_argument("--no-mask", action="store_true", help="use every pixel, even where mask.png says not to")
    p.add_argument("--device", default="auto", help="auto, cpu, cuda, cuda:N (default auto)")
    add_amp_argument(p)


def _ride_args(c: argparse.ArgumentParser) -> None:
    """The options of an export of a whole ride: its input and the odometry that poses it (every option
    of ``cylsfm odometry``)."""
    c.add_argument("input", metavar="INPUT", help="a video file, a folder of frames, or a dataset sequence")
    c.add_argument("--checkpoint", required=True, help="checkpoint file or run directory")
    c.add_argument(
        "--odometry",
        metavar="DIR",
        help="the poses of this finished output of cylsfm odometry (made with the same input, checkpoint "
        "and options, which its fingerprint must confirm) instead of running the odometry again",
    )
    add_ride_options(c)


def _colmap_args(sub) -> None:
    c = sub.add_parser(
        "colmap",
        help="a ride as a COLMAP model and a nerfstudio transforms.json (virtual pinhole views, posed by the "
        "ride's odometry, with points from the depth): for Gaussian splatting and NeRF trainers",
    )
    _ride_args(c)
    c.add_argument(
        "out",
        metavar="OUT",
        help="the folder to write: images/, sparse/0/, transforms.json (the odometry, unless --odometry, "
        "goes to OUT/odometry/)",
    )
    c.add_argument("--views", type=int, default=4, help="pinhole views per pitch, turned evenly (default 4)")
    c.add_argument(
        "--pitches",
        type=_degrees_list,
        default=(0.0,),
        metavar="DEG[,DEG...]",
        help="the views' tilts in degrees, positive up, each with --views views (default 0: level); "
        "tilts beyond the frames' field of view need equirectangular input, e.g. 0,-45,45",
    )
    c.add_argument("--fov", type=float, default=90.0, help="the views' horizontal field of view (default 90)")
    c.add_argument("--view-size", type=int, default=512, help="the views' width and height (default 512)")
    c.add_argument("--points-per-frame", type=int, default=2000, help="3D points from each depth map")
    c.add_argument("--image-format", choices=["jpg", "png"], default="jpg", help="the views' files")
    c.add_argument("--text", action="store_true", help="also write the COLMAP model as text")
    r = sub.add_parser(
        "rerun",
        help="a ride as a rerun recording (.rrd): the trajectory, the panoramas and depth on a time line, "
        "the back-projected coloured points",
    )
    _ride_args(r)
    r.add_argument(
        "out",
        metavar="OUT.rrd",
        help="the recording to write (the odometry, unless --odometry, goes to OUT.rrd.odometry/)",
    )
    r.add_argument("--points-per-frame", type=int, default=4000, help="3D points from each depth map")


def _degrees_list(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected degrees separated by commas, got {text!r}") from None


def _export_args(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", required=True, metavar="{onnx,mesh,stereo,viewer,colmap,rerun}")
    onnx = sub.add_parser(
        "onnx",
        help="the depth network as ONNX (image [B,3,H,W] in [0,1] -> depth [B,1,H,W]), wrap padding in "
        "standard operators",
    )
    onnx.add_argument("--checkpoint", required=True, help="checkpoint file or run directory")
    onnx.add_argument("--out", required=True, help="the .onnx file to write")
    onnx.add_argument("--opset", type=int, default=18, help="ONNX operator set (default 18)")
    onnx.add_argument("--no-check", action="store_true", help="do not compare with PyTorch in ONNX Runtime")

    mesh = sub.add_parser("mesh", help="a panorama's depth as a coloured triangle mesh or point cloud (PLY)")
    mesh.add_argument("pano", metavar="PANO", help="the panorama (cylindrical or equirectangular image)")
    mesh.add_argument("out", metavar="OUT.ply", help="the PLY file to write")
    _depth_source(mesh)
    mesh.add_argument("--points", action="store_true", help="a point cloud (vertices only)")
    mesh.add_argument(
        "--max-ratio",
        type=float,
        default=1.2,
        help="leave out triangles whose corners' depths differ by more than this ratio (default 1.2)",
    )
    mesh.add_argument("--max-depth", type=float, help="leave out pixels farther than this (e.g. the sky)")
    _vertices_arg(mesh)

    _colmap_args(sub)
    st = sub.add_parser("stereo", help="omni-directional stereo panoramas (image or video) for VR")
    st.add_argument("pano", metavar="PANO", help="a panorama image, or a video (needs --checkpoint)")
    st.add_argument("out", metavar="OUT", help="the image (.png) or video (.mp4) to write")
    _depth_source(st)
    st.add_argument("--ipd", type=float, default=0.064, help="distance between the eyes (default 0.064)")
    st.add_argument("--layout", choices=["top-bottom", "side-by-side"], default="top-bottom")
    st.add_argument("--equirect", action="store_true", help="equirectangular eyes (what players expect)")
    st.add_argument("--anaglyph", action="store_true", help="also write OUT_anaglyph.png (red-cyan)")
    st.add_argument("--width", type=int, help="the eyes' width in pixels (default: the depth's)")
    st.add_argument(
        "--median-depth",
        type=float,
        default=3.0,
        help="relative depth is scaled to this median (one scale per video; default 3)",
    )
    st.add_argument("--fps", type=float, help="videos: about N frames a second (default: every frame)")
    st.add_argument("--no-progress", action="store_true", help="no progress bar")
    _viewer_args(sub)


def _viewer_args(sub) -> None:
    vw = sub.add_parser("viewer", help="a self-contained web page to look around the 3D reconstruction")
    vw.add_argument("pano", metavar="PANO", help="the panorama")
    vw.add_argument("out", metavar="OUT_DIR", help="the folder to write (index.html and what it needs)")
    _depth_source(vw)
    vw.add_argument("--trajectory", help="a TUM trajectory (e.g. from cylsfm odometry) shown in the scene")
    vw.add_argument("--max-ratio", type=float, default=1.2, help="as for export mesh (default 1.2)")
    _vertices_arg(vw)
    vw.add_argument(
        "--texture-width",
        type=int,
        default=4096,
        help="the colour texture's largest width (default 4096; the panorama's own width when smaller)",
    )


def _vertices_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--vertices",
        type=int,
        default=262_144,
        help="vertex budget: the depth is brought to the largest size with at most this many pixels (up to "
        "the panorama's own width), upsampled guided by the panorama's colours (default 262144)",
    )


@command(
    "export",
    "export a model (ONNX), a panorama's depth (mesh, VR stereo, web viewer) or a ride (COLMAP, rerun)",
    _export_args,
)
def run_export(args: argparse.Namespace) -> int:
    if args.action == "onnx":
        return _onnx(args)
    if args.action in ("colmap", "rerun"):
        return _ride(args)
    from ..export.scene import load_scene

    if args.action == "stereo" and _is_video(args.pano):
        return _stereo_video(args)
    mask = False if args.no_mask else args.mask
    scene = load_scene(args.pano, args.depth, args.checkpoint, args.camera, args.device, mask, args.amp)
    if args.camera_height is not None and args.action != "stereo":
        scene = scene.to_metres(args.camera_height)
    if args.action == "mesh":
        from ..export.mesh import build_mesh, write_ply

        mesh = build_mesh(scene.within(args.vertices), args.max_ratio, args.max_depth)
        comments = [
            f"cylsfm export mesh of {args.pano}",
            f"scale: {scene.scale_note}",
            "axes: x right, y down, z forward",
        ]
        write_ply(mesh, args.out, comments, points=args.points)
        what = "points" if args.points else f"vertices, {len(mesh.faces)} triangles"
        print(f"wrote {args.out}: {len(mesh.vertices)} {what} ({scene.unit})")
        return 0
    if args.action == "viewer":
        from ..export.viewer import export_viewer

        page = export_viewer(
            scene,
            args.out,
            args.max_ratio,
            args.trajectory,
            title=args.pano,
            vertices=args.vertices,
            texture_width=args.texture_width,
        )
        print(f"wrote {page} (open it in a browser; no server needed)")
        return 0
    from ..export.stereo import export_stereo_image

    for path in export_stereo_image(scene, args.out, _stereo_options(args)):
        print(f"wrote {path}")
    return 0


def _is_video(path: str) -> bool:
    from pathlib import Path

    from ..data.inputs import discover_inputs

    return Path(path).is_file() and discover_inputs([path])[0].kind == "video"


def _stereo_options(args: argparse.Namespace):
    from ..export.stereo import StereoOptions

    return StereoOptions(
        ipd=args.ipd,
        layout=args.layout,
        equirect=args.equirect,
        anaglyph=args.anaglyph,
        width=args.width,
        camera_height=args.camera_height,
        median_depth=args.median_depth,
    )


def _stereo_video(args: argparse.Namespace) -> int:
    from ..errors import InputError
    from ..export.scene import scene_function
    from ..export.stereo import export_stereo_video

    if args.checkpoint is None:
        raise InputError(f"{args.pano}: stereo from a video needs --checkpoint (depth for every frame)")
    from ..model.checkpoint import checkpoint_id
    from ..runtime import file_id

    scene_of = scene_function(args.pano, args.checkpoint, args.camera, args.device, args.mask, args.amp)
    identity = {
        "checkpoint": checkpoint_id(args.checkpoint),
        "camera": file_id(args.camera) if args.camera else None,
        "mask": file_id(args.mask) if args.mask else None,
    }
    path, note = export_stereo_video(
        args.pano, args.out, scene_of, _stereo_options(args), args.fps, not args.no_progress, identity
    )
    print(f"wrote {path} ({note})")
    return 0


def _ride(args: argparse.Namespace) -> int:
    from ..export.colmap import ViewOptions
    from ..odometry import export_colmap, export_rerun

    settings = ride_settings(args)
    if args.action == "rerun":
        s = export_rerun(
            args.input, args.checkpoint, args.out, settings, args.points_per_frame, args.odometry
        )
        print(f"wrote {s['path']}: {s['frames']} frames ({s['unit']}); open it with: rerun {s['path']}")
        return 0
    views = ViewOptions(
        yaws=args.views,
        pitches=args.pitches,
        fov=args.fov,
        width=args.view_size,
        points_per_frame=args.points_per_frame,
        image_format=args.image_format,
        text=args.text,
    )
    s = export_colmap(args.input, args.checkpoint, args.out, settings, views, args.odometry)
    print(
        f"wrote {args.out}: {s['images']} views of {s['panoramas']} panoramas, {s['points']} points ({s['unit']}); "
        "COLMAP model in sparse/0, nerfstudio's transforms.json"
    )
    return 0


def _onnx(args: argparse.Namespace) -> int:
    from ..export.onnx import export_depth_onnx

    result = export_depth_onnx(args.checkpoint, args.out, opset=args.opset, check=not args.no_check)
    w, h = result.size
    print(f"wrote {result.path}: image [B,3,{h},{w}] in [0, 1] -> depth [B,1,{h},{w}] (network units)")
    if not args.no_check:
        print(
            f"ONNX Runtime against PyTorch on two test panoramas: max |difference| {result.max_abs_diff:.3g} "
            f"(relative {result.max_rel_diff:.3g})"
        )
    return 0
