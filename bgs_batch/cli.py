"""The `bgs` command line: one Click group, thin commands over the library.

Exit codes: 0 ok, 1 internal error, 2 usage error, 3 invalid input, 4 output exists,
5 job directory busy or made for other inputs, 6 the file system refused (full, read-only,
permission), 75 job stopped after a checkpoint, 128+N interrupted by signal N (see
`bgs_batch.errors`).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from bgs_batch import __version__
from bgs_batch.errors import BgsError, file_system_error

DEMO_FRAMES = 30  # `make demo` from a clean clone (set-up, JIT, run, export) in < 5 min on 2 cores

class _UserError(click.ClickException):
    """A `BgsError` shown as ``Error: message`` with its own exit code, no traceback."""

    def __init__(self, err: BgsError) -> None:
        super().__init__(str(err))
        self.exit_code = err.exit_code


class ImageSize(click.ParamType):
    """``WxH`` on the command line, e.g. ``640x480``."""

    name = "WxH"

    def convert(self, value, param, ctx):  # noqa: ANN001, ANN201 - Click's signature
        if isinstance(value, tuple):
            return value
        try:
            width, height = (int(v) for v in value.lower().split("x"))
        except ValueError:
            self.fail(f"{value!r} is not WIDTHxHEIGHT, e.g. 640x480", param, ctx)
        return width, height


class Readout(click.ParamType):
    """Seconds, or ``auto`` where allowed (NaN in the store: `bgs run` estimates the readout)."""

    def __init__(self, auto: bool = True) -> None:
        self.auto = auto
        self.name = "SECONDS|auto" if auto else "SECONDS"

    def convert(self, value, param, ctx):  # noqa: ANN001, ANN201 - Click's signature
        if isinstance(value, float):
            return value
        if self.auto and str(value).strip().lower() == "auto":
            return math.nan
        either = " nor auto" if self.auto else ""
        try:
            seconds = float(value)
        except ValueError:
            self.fail(f"{value!r} is not seconds (e.g. 0.03){either}", param, ctx)
        from bgs_batch.store import MAX_READOUT_S

        if not 0 <= seconds < MAX_READOUT_S:
            self.fail(f"{value} s is not a readout: use 0 <= SECONDS < {MAX_READOUT_S:g}"
                      + (", or auto" if self.auto else ""), param, ctx)  # fmt: skip
        return seconds


class BgsGroup(click.Group):
    """Click group that reports library errors, and the file system's refusals, as one line
    naming the file and the fix, with their exit codes (`bgs_batch.errors`); `-v` adds the
    traceback."""

    def invoke(self, ctx: click.Context):  # noqa: ANN201 - Click's signature
        try:
            return super().invoke(ctx)
        except BgsError as err:
            logging.getLogger("bgs").debug("details", exc_info=True)  # the traceback with -v
            raise _UserError(err) from err
        except OSError as err:  # disk full, read-only, permission denied: the user's to fix
            user_error = file_system_error(err)
            if user_error is None:
                raise
            logging.getLogger("bgs").debug("details", exc_info=True)
            raise _UserError(user_error) from err


def _show_progress(ctx: click.Context) -> bool:
    return not ctx.find_root().params.get("quiet", False)


@click.group(cls=BgsGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="bgs")
@click.option("-q", "--quiet", is_flag=True, help="No progress bars; only results and errors.")
@click.option("-v", "--verbose", is_flag=True, help="Log details of every step.")
def main(quiet: bool, verbose: bool) -> None:
    """bgs-batch: uncertainty-aware 3D Gaussian Splatting SLAM for RGB-D recordings, on CPU.

    \b
    The data flow, one command per step:
      bgs synth demo/seq             make a synthetic TUM-layout sequence
      bgs convert tum DIR -o seq.h5  recording -> frame store (HDF5)
      bgs inspect seq.h5             check a store and summarise it
      bgs demo                       all of the above on a small sequence

    Run `bgs COMMAND --help` for each command's options and an example.
    """
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.WARNING, format="%(levelname)s %(message)s"
    )


@main.group()
def convert() -> None:
    """Convert a recording into a frame store (one HDF5 file per sequence).

    \b
    Example:
      bgs convert tum rgbd_dataset_freiburg1_rpy -o fr1_rpy.h5
    """


def _readout_options(default: str) -> Callable[[Callable], Callable]:
    """``--readout`` and ``--depth-readout`` of a converter whose default is `default`."""

    def add(command: Callable) -> Callable:
        command = click.option(
            "--depth-readout", type=Readout(auto=False),
            help="The depth image's readout when its sensor reads out otherwise than the "
                 "colour one, e.g. 0 for a RealSense D435's global-shutter depth with "
                 "--readout auto (or its colour readout). Default: --readout's.")(command)
        return click.option(
            "--readout", type=Readout(),
            help="Seconds over which the camera reads an image's rows out (rolling shutter; "
                 "0: global shutter), or auto: `bgs run` estimates it from the frames. "
                 f"Default: {default}. `bgs run` moves the rows to one instant.")(command)

    return add


def _conversion_options(command: Callable) -> Callable:
    """The options every `convert` command shares (output, subsampling, robustness, threads)."""
    for option in reversed((
        click.option("-o", "--output", type=click.Path(path_type=Path),
                     help="Frame store to write [default: ./<input name>.h5]."),
        click.option("--stride", default=1, show_default=True, type=click.IntRange(min=1),
                     help="Keep every STRIDE-th frame."),
        click.option("--max-frames", type=click.IntRange(min=1),
                     help="Stop after this many frames."),
        click.option("--skip-bad-frames", is_flag=True,
                     help="Drop undecodable frames (listed in the report and store) instead of "
                          "failing."),
        click.option("--overwrite", is_flag=True, help="Replace OUTPUT if it exists."),
        click.option("--workers", default=2, show_default=True, type=click.IntRange(min=1),
                     help="Decode/compress threads."),
    )):  # fmt: skip
        command = option(command)
    return command


def _convert_plan(ctx: click.Context, source: Path, output: Path | None, options: dict,
                  plan_fn: Callable, options_type: type) -> None:  # fmt: skip
    """Plan with ``plan_fn(source, options_type(**options))``, write the store and report."""
    from bgs_batch.progress import progress_bar
    from bgs_batch.store import check_output_path
    from converters.pipeline import write_store

    source = Path(source).resolve()
    output = output or Path(f"{source.stem if source.is_file() else source.name}.h5")
    overwrite, skip, workers = (options.pop(k) for k in ("overwrite", "skip_bad_frames", "workers"))
    check_output_path(output, overwrite)
    plan = plan_fn(source, options_type(**options))
    for note in getattr(plan, "notes", ()):
        click.echo(note, err=note.startswith("warning"))
    with progress_bar("converting", plan.count, _show_progress(ctx)) as advance:
        report = write_store(plan.frames, output, plan.meta, overwrite=overwrite,
                             skip_bad_frames=skip, workers=workers, progress=advance)  # fmt: skip
    for item in report.skipped:
        click.echo(f"skipped {item['frame']}: {item['reason']}", err=True)
    click.echo(f"wrote {report.path} ({report.frames} frames, {len(report.skipped)} skipped, "
               f"{report.frames / report.seconds:.1f} frames/s)")  # fmt: skip


@convert.command("tum")
@click.argument("folder", type=click.Path(path_type=Path))
@click.option("--tolerance", default=0.02, show_default=True, type=click.FloatRange(min=0),
              help="Max RGB-depth timestamp difference (s) for an association. Free-running "
                   "30 Hz streams are at most 17 ms apart, and the order-preserving matching "
                   "keeps every such pair (all frames of the fr1/rpy pieces tried, where the "
                   "nearest-first matching of TUM's associate.py drops up to 12 %); a wider "
                   "tolerance only adds pairs whose colour and depth show different moments.")
@click.option("--intrinsics", nargs=4, type=float, metavar="FX FY CX CY",
              help="Override the camera (default: calibration.txt, else the published "
                   "freiburg1/2/3 calibration picked from the folder name).")
@click.option("--distortion", nargs=5, type=float, metavar="K1 K2 P1 P2 K3",
              help="Override the distortion coefficients (OpenCV order).")
@click.option("--undistort/--no-undistort", default=True, show_default=True,
              help="Undistort RGB (bilinear) and depth (nearest) before storing, when the "
                   "camera's distortion is known and not zero (freiburg1/2, --distortion).")
@click.option("--depth-scale", default=5000.0, show_default=True,
              type=click.FloatRange(min=0, min_open=True),
              help="Units per metre of the depth PNGs: 5000 for TUM RGB-D, 1000 (millimetres) "
                   "for most RealSense, Azure Kinect and OpenLORIS exports in this layout.")
@_readout_options("readout.txt, else 0.03 for the freiburg1/2/3 Kinect-class cameras, else auto")
@_conversion_options
@click.pass_context
def convert_tum(ctx: click.Context, folder: Path, output: Path | None, **options) -> None:
    """Convert a TUM RGB-D sequence folder (rgb.txt, depth.txt, groundtruth.txt).

    RGB and depth are associated one to one in time order (the most pairs within --tolerance,
    then the closest); the summary line says how many RGB images had no depth image. Ground
    truth is interpolated to each RGB frame (linear position, slerp rotation) where samples
    bracket it within 0.1 s, else NaN. Images of a freiburg1/2 camera are undistorted with its
    published coefficients, and the store records the border the reference SLAM systems crop
    for the camera (fr1 50 px, fr2 and fr3 8 px), which `bgs run` applies by default.

    \b
    Example:
      bgs convert tum data/rgbd_dataset_freiburg1_rpy -o fr1_rpy.h5 --max-frames 100
      bgs convert tum my_realsense_export --intrinsics 615 615 320 240 --depth-scale 1000
    """
    from converters.tum import TumOptions, plan_tum

    options["intrinsics"] = options["intrinsics"] or None
    options["distortion"] = options["distortion"] or None
    _convert_plan(ctx, folder, output, options, plan_tum, TumOptions)


@convert.command("scannet")
@click.argument("path", type=click.Path(path_type=Path))
@_readout_options("auto")
@_conversion_options
@click.pass_context
def convert_scannet(ctx: click.Context, path: Path, output: Path | None, **options) -> None:
    """Convert a ScanNet scene: an exported folder or the raw .sens file (streamed).

    The folder holds color/*.jpg, depth/*.png (mm), pose/*.txt (camera-to-world) and
    intrinsic/intrinsic_depth.txt. Colour is resized to the depth resolution (area averaging) and
    the depth intrinsics are stored; invalid (-inf) poses become NaN and the frames are kept.
    Timestamps are frame index / 30 Hz, as exports carry none. The store records the reference
    systems' 12 px border crop for 640x480 frames, which `bgs run` applies by default, and the
    readout as unknown unless --readout gives it: `bgs run` estimates it from the frames.

    \b
    Example:
      bgs convert scannet scans/scene0000_00/scene0000_00.sens -o scene0000_00.h5
      bgs convert scannet exports/scene0000_00 --stride 5
    """
    from converters.scannet import ScanNetOptions, plan_scannet

    _convert_plan(ctx, path, output, options, plan_scannet, ScanNetOptions)


@convert.command("bag")
@click.argument("path", type=click.Path(path_type=Path))
@click.option("--rgb-topic", help="Colour image topic [default: the only colour topic].")
@click.option("--depth-topic", help="Depth image topic [default: the only depth topic].")
@click.option("--info-topic", help="Colour CameraInfo topic [default: the one beside RGB].")
@click.option("--depth-info-topic",
              help="Depth CameraInfo topic [default: the one beside depth; none: registered].")
@click.option("--pose-topic",
              help="Ground-truth poses: PoseStamped, PoseWithCovarianceStamped, Odometry, "
                   "TransformStamped or TF (with --pose-frame).")
@click.option("--pose-frame", help="Child frame to take from a TF --pose-topic.")
@click.option("--tolerance", default=0.02, show_default=True, type=click.FloatRange(min=0),
              help="Max RGB-depth header-stamp difference (s) for an association.")
@click.option("--depth-scale", type=click.FloatRange(min=0, min_open=True),
              help="Units per metre of 16-bit depth [default: RealSense option, else 1000].")
@_readout_options("auto")
@_conversion_options
@click.pass_context
def convert_bag(ctx: click.Context, path: Path, output: Path | None, **options) -> None:
    """Convert a ROS1 .bag, ROS2 .db3/.mcap file or ROS2 bag folder (streamed, two passes).

    Topics are auto-detected (an error lists them when the choice is ambiguous). Images may be
    raw (rgb8, bgr8, rgba8, bgra8, mono8; 16UC1/mono16 mm, 32FC1 m) or compressed (JPEG, PNG,
    compressedDepth). RGB and depth are associated by header stamp; depth with its own
    intrinsics is registered into the colour camera with the extrinsic from /tf_static, /tf or
    the RealSense tf/0 topics.

    \b
    Example:
      bgs convert bag recording.bag -o seq.h5 --tolerance 0.15
      bgs convert bag rosbag2_run/ --rgb-topic /camera/color/image_raw \\
          --depth-topic /camera/aligned_depth_to_color/image_raw --pose-topic /vicon/pose
    """
    from converters.bag import BagOptions, plan_bag

    _convert_plan(ctx, path, output, options, plan_bag, BagOptions)


@main.command()
@click.argument("store", type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@click.option("--verify", is_flag=True,
              help="Only decode every chunk of every frame (threaded) and list each damaged "
                   "frame, instead of stopping at the first.")
@click.option("--workers", default=2, show_default=True, type=click.IntRange(min=1),
              help="Decode threads of --verify.")
def inspect(store: Path, as_json: bool, verify: bool, workers: int) -> None:
    """Validate a frame store and summarise it.

    Prints frames, resolution, duration, frame rate, depth validity, ground-truth coverage,
    intrinsics and the provenance of every conversion choice. Exits with code 3 when the store
    is invalid or a frame does not decode (--verify lists them all).

    \b
    Example:
      bgs inspect fr1_rpy.h5
      bgs inspect --verify fr1_rpy.h5
    """
    from bgs_batch.errors import InputError
    from bgs_batch.store import FrameStore
    from bgs_batch.store_summary import print_summary, summarize

    with FrameStore(store) as opened:
        if verify:
            damaged = opened.damaged_frames(workers)
            for index, problem in damaged:
                click.echo(f"frame {index}: {problem}")
            if damaged:
                raise InputError(f"{store}: {len(damaged)} of {len(opened)} frames are damaged; "
                                 "re-create the store with `bgs convert …`")  # fmt: skip
            click.echo(f"{store}: all {len(opened)} frames decode")
            return
        summary = summarize(opened)
    if as_json:
        click.echo(json.dumps(summary.as_dict(), indent=2))
    else:
        print_summary(summary)


@main.command()
@click.argument("out_dir", type=click.Path(path_type=Path))
@click.option("--frames", default=60, show_default=True, type=click.IntRange(min=2),
              help="Number of RGB-D frames.")
@click.option("--size", default="320x240", show_default=True, type=ImageSize(),
              help="Image size WIDTHxHEIGHT.")
@click.option("--seed", default=0, show_default=True, type=int,
              help="Scene, path and noise seed; the same seed gives byte-identical files.")
@click.option("--loop", is_flag=True, help="Make the camera path return to its start.")
@click.option("--motion", type=click.Choice(["handheld", "walk", "shake"]), default="handheld",
              show_default=True,
              help="handheld: TUM handheld speeds; walk: faster, smoother, mostly turning "
                   "left and right; shake: little travel, fast roll/pitch/yaw like TUM fr1/rpy.")
@click.option("--blur", is_flag=True, help="Motion blur: colour exposed over half a frame.")
@click.option("--rolling-shutter", is_flag=True,
              help="Rows read out top to bottom over 0.9 of a frame (colour and depth); the "
                   "readout goes to readout.txt, which `bgs convert tum` records.")
@click.option("--global-shutter-depth", is_flag=True,
              help="With --rolling-shutter: the depth image is taken at once, only the colour "
                   "rows are read out over time (as a RealSense D435's sensors).")
@click.option("--holes", is_flag=True, help="Large depth holes (15 percent of the image).")
@click.option("--misregister", is_flag=True,
              help="A colour camera 6 mm beside the depth camera, turned by 1.6 degrees, its "
                   "focal length 3 percent longer; calibration.txt gives the depth camera's "
                   "intrinsics for both, as a pair of cameras never registered to each other.")
@click.option("--overwrite", is_flag=True, help="Replace OUT_DIR if it exists.")
@click.pass_context
def synth(ctx: click.Context, out_dir: Path, frames: int, size: tuple[int, int], seed: int,
          loop: bool, motion: str, blur: bool, rolling_shutter: bool,
          global_shutter_depth: bool, holes: bool, misregister: bool,
          overwrite: bool) -> None:  # fmt: skip
    """Render a synthetic RGB-D sequence of a textured room, in TUM layout.

    Open3D ray casting of a room with furniture, a smooth camera path, Kinect-like depth noise
    and holes, exact ground truth (groundtruth.txt), intrinsics (calibration.txt) and the
    standard deviation of the noise at every depth reading (depth_sigma/, 16-bit PNGs in units
    of 10 µm, named like the depth images: a truth to score sensor-noise models against). The
    ground-truth pose of a frame is the camera's at its time stamp: the middle of the exposure
    of the middle row.

    \b
    Examples:
      bgs synth demo/room --frames 120 --size 640x480 --seed 3 --loop
      bgs synth demo/shaky --motion shake --blur --rolling-shutter --holes
      bgs convert tum demo/room -o room.h5
    """
    from bgs_batch.progress import progress_bar
    from converters.synthetic import motion_config, synthesize

    if global_shutter_depth and not rolling_shutter:
        raise click.UsageError("--global-shutter-depth needs --rolling-shutter (the colour "
                               "image's readout)")  # fmt: skip
    effects = tuple(name for name, on in (
        ("blur", blur), ("rolling_shutter", rolling_shutter),
        ("global_shutter_depth", global_shutter_depth), ("holes", holes),
        ("misregister", misregister)) if on)  # fmt: skip
    config = motion_config(motion, effects, frames=frames, width=size[0], height=size[1],
                           seed=seed, loop=loop)  # fmt: skip
    with progress_bar("rendering", frames, _show_progress(ctx)) as advance:
        synthesize(out_dir, config, overwrite=overwrite, progress=lambda _d, _t: advance(1))
    click.echo(f"wrote {frames} frames to {out_dir}")


@main.command()
@click.option("--dir", "workdir", default="demo", show_default=True,
              type=click.Path(path_type=Path), help="Folder for the demo's outputs (replaced).")
@click.option("--frames", default=DEMO_FRAMES, show_default=True, type=click.IntRange(min=2))
@click.option("--size", default="320x240", show_default=True, type=ImageSize())
@click.pass_context
def demo(ctx: click.Context, workdir: Path, frames: int, size: tuple[int, int]) -> None:
    """Run the whole pipeline on a small synthetic sequence and show where the outputs are.

    \b
    Example:
      bgs demo --frames 30 --size 160x120
    """
    from bgs_batch.demo import DemoConfig, run_demo

    config = DemoConfig(workdir=workdir, frames=frames, width=size[0], height=size[1])
    run_demo(config, show_progress=_show_progress(ctx))


def _frame_options(command: Callable) -> Callable:
    """Options `export` and `eval` share: the store, the resolution, LPIPS weights."""
    for option in reversed((
        click.option("--store", type=click.Path(path_type=Path),
                     help="The job's frame store (images, ground truth) [default: the store "
                          "recorded in JOB/job.json, if still there]."),
        click.option("--downscale", type=click.IntRange(min=1),
                     help="Render and evaluate at input resolution / N [default: the run's "
                          "mapping resolution, where the SLAM computed its variances]."),
        click.option("--lpips-weights", multiple=True, type=click.Path(path_type=Path),
                     help="LPIPS weights (state dict; repeatable to merge a torchvision "
                          "backbone with lpips's linear heads). Without it LPIPS is not "
                          "computed; nothing is ever downloaded."),
    )):  # fmt: skip
        command = option(command)
    return command


def _print_export(report, brief_in: Path | None = None) -> None:  # noqa: ANN001 - ExportReport
    """What an export wrote (or, with `brief_in`, one line naming the files of that folder) and
    its headline metrics."""
    if brief_in is not None:
        names = sorted({p.relative_to(brief_in).parts[0] for p in report.files})
        click.echo(f"exported into {brief_in}: {', '.join(names)}")
    for path in [] if brief_in is not None else report.files:
        count = report.gaussians.get(path.name)
        click.echo(f"wrote {path}" + ("" if count is None else f" ({count} Gaussians)"))
    if report.handoff is not None:
        h = report.handoff
        click.echo(f"{h.folder}: {h.images} images, {h.points} points, {h.observations} "
                   "observations (COLMAP model in sparse/0)")  # fmt: skip
    for alignment, stats in report.ate.items():
        rmse = "n/a (degenerate)" if math.isnan(stats["rmse"]) else f"{stats['rmse'] * 100:.2f} cm"
        click.echo(f"ATE RMSE ({alignment.replace('_', ' ')}): {rmse} "
                   f"over {stats['frames']} frames")  # fmt: skip
    metrics = report.metrics
    if metrics:
        r, u = metrics["rendering"], metrics["uncertainty"]
        line = f"submaps at keyframes: PSNR {r['psnr_db']:.2f} dB, SSIM {r['ssim']:.3f}"
        if r["depth_l1_cm"] is not None:
            line += f", depth L1 {r['depth_l1_cm']:.2f} cm"
        if u is not None:
            line += (f", AUSE-MAE colour {u['ause_mae_color']['ause_raw']:.4f}, depth "
                     f"{u['ause_mae_depth']['ause_raw']:.4f} m (raw)")  # fmt: skip
        click.echo(line)
        g = metrics["global_map"]
        parts = []
        for name, label in (("held_out", "held-out frames"), ("keyframes", "keyframes")):
            r = g[name]["rendering"]
            if r["frames"]:
                parts.append(f"{label} PSNR {r['psnr_db']:.2f} dB, SSIM {r['ssim']:.3f}")
        if parts:
            click.echo(f"global map ({g['gaussians']} Gaussians, input resolution): "
                       + "; ".join(parts))  # fmt: skip


def _run_export(ctx: click.Context, job: Path, options, brief: bool = False) -> None:  # noqa: ANN001
    from bgs_batch.progress import progress_bar
    from outputs.export import export_job, frames_to_render
    from outputs.jobfiles import FinishedJob

    count = 0
    if options.uncertainty or options.renders or options.report or options.colmap:
        count = frames_to_render(FinishedJob(job, options.store), options).count
    with progress_bar("rendering", count, _show_progress(ctx) and count > 0) as advance:
        report = export_job(job, options, progress=advance)
    _print_export(report, job / "outputs" if brief else None)


@main.command()
@click.argument("job", type=click.Path(path_type=Path))
@click.option("--ply", is_flag=True, help="Write the submap and merged-map PLY files.")
@click.option("--trajectory", is_flag=True,
              help="Write the trajectories (TUM and KITTI; aligned and GT when GT exists).")
@click.option("--uncertainty", is_flag=True,
              help="Write uncertainty.h5 (renders, variances, residuals; float32) and "
                   "colour-mapped PNGs with colour bars.")
@click.option("--renders", is_flag=True,
              help="Write rendered colour (8-bit PNG) and depth (16-bit PNG, 5000 per m).")
@click.option("--report", is_flag=True,
              help="Evaluate (metrics.json, as `bgs eval`) and write report.html with its plots.")
@click.option("--colmap", is_flag=True,
              help="Write colmap/ for the splat trainers: the frames as the run saw them "
                   "(images/, 16-bit mm depths/) and a COLMAP model (sparse/0: one PINHOLE "
                   "camera, trajectory.txt's poses, the global map's points with tracks).")
@click.option("--nerfstudio", is_flag=True,
              help="Also nerfstudio's transforms.json and sparse_pc.ply in colmap/ (implies "
                   "--colmap).")
@click.option("--text", is_flag=True, help="Also the COLMAP model as .txt (implies --colmap).")
@click.option("--frames", "which", type=click.Choice(["keyframes", "all"]), default="keyframes",
              show_default=True, help="Frames of the uncertainty images, renders and colmap/.")
@click.option("--stride", default=1, show_default=True, type=click.IntRange(min=1),
              help="Keep every STRIDE-th of those frames.")
@_frame_options
@click.pass_context
def export(ctx: click.Context, job: Path, ply: bool, trajectory: bool, uncertainty: bool,
           renders: bool, report: bool, colmap: bool, nerfstudio: bool, text: bool, which: str,
           stride: int, store: Path | None, downscale: int | None,
           lpips_weights: tuple[Path, ...]) -> None:  # fmt: skip
    """Write a finished job's outputs into JOB/outputs (all of them when no flag is given).

    PLY files use the INRIA 3DGS layout (opacity logit, log scales, w-first quaternion, SH DC)
    plus a float `uncertainty` property; trajectories are camera-to-world, TUM and KITTI. The
    aligned estimate is rigidly aligned to GT (rotation + translation, no scale), as
    `evo_ape tum gt.tum estimate.tum -a`. Uncertainty images are re-rendered from the saved
    submaps, poses and sensor network with the SLAM's own variance formula. colmap/ is what
    the 3DGS, gsplat and nerfstudio trainers read (COLMAP's pixel convention: the principal
    point is the run's plus half a pixel). Every file is written under a temporary name and
    renamed when complete.

    \b
    Example:
      bgs export jobs/fr1_rpy --store fr1_rpy.h5
      bgs export jobs/fr1_rpy --uncertainty --frames all --stride 5
      bgs export jobs/fr1_rpy --ply
      bgs export jobs/fr1_rpy --colmap --nerfstudio     # then train a splat model on colmap/
    """
    from outputs.export import ExportOptions

    colmap = colmap or nerfstudio or text
    everything = not (ply or trajectory or uncertainty or renders or report or colmap)
    options = ExportOptions(
        ply=ply or everything, trajectory=trajectory or everything,
        uncertainty=uncertainty or everything, renders=renders or everything,
        metrics=report or everything, report=report or everything,
        colmap=colmap or everything, nerfstudio=nerfstudio or everything, text=text,
        frames=which, stride=stride, downscale=downscale, lpips_weights=lpips_weights,
        store=store,
    )  # fmt: skip
    _run_export(ctx, job, options)


@main.command("eval")
@click.argument("job", type=click.Path(path_type=Path))
@click.option("--no-report", is_flag=True, help="Write metrics.json only (no report.html).")
@_frame_options
@click.pass_context
def evaluate(ctx: click.Context, job: Path, no_report: bool, store: Path | None,
             downscale: int | None, lpips_weights: tuple[Path, ...]) -> None:  # fmt: skip
    """Evaluate a finished job: JOB/outputs/metrics.json and report.html.

    ATE (rigid and with-scale alignment), PSNR, SSIM, MS-SSIM, depth L1 and (with
    --lpips-weights) LPIPS on the keyframes, AUSE-MAE of colour and depth (raw and normalised,
    with the sparsification curves), keyframes, mapping calls and time per stage. metrics.json
    states every convention. The report embeds its plots and a gallery of uncertainty images.

    \b
    Example:
      bgs eval jobs/fr1_rpy
      bgs eval jobs/fr1_rpy --downscale 1 --lpips-weights lpips_alex.pth
    """
    from outputs.export import ExportOptions

    options = ExportOptions(ply=False, trajectory=False, uncertainty=False, renders=False,
                            metrics=True, report=not no_report, downscale=downscale,
                            lpips_weights=lpips_weights, store=store)  # fmt: skip
    _run_export(ctx, job, options)


@main.command()
@click.argument("store", type=click.Path(path_type=Path))
@click.option("--job-dir", required=True, type=click.Path(path_type=Path),
              help="Folder for the job's outputs (created).")
@click.option("--preset", default="cpu", show_default=True,
              help="Settings preset: 'cpu' (tuned for 2 cores) or 'paper' (published settings).")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
              help="Override one setting, e.g. --set tracking.iterations=100 (repeatable).")
@click.option("--max-frames", type=click.IntRange(min=1), help="Process only the first N frames.")
@click.option("--force", is_flag=True,
              help="Start the job over: move JOB_DIR's previous run aside whole (to "
                   "JOB_DIR.replaced-<time>) and run from frame 0 with this store and these "
                   "settings.")
@click.option("--no-export", is_flag=True,
              help="Skip the default export at the end (PLY, trajectories, uncertainty images "
                   "of the keyframes, metrics.json, report.html; see `bgs export`).")
@click.pass_context
def run(ctx: click.Context, store: Path, job_dir: Path, preset: str, overrides: tuple[str, ...],
        max_frames: int | None, force: bool, no_export: bool) -> None:  # fmt: skip
    """Run uncertainty-aware Gaussian-splatting SLAM on a frame store.

    Writes config.json, log.jsonl (one event per frame: pose, keyframe decision with both
    surprise scores, losses), trajectory.txt (TUM format), submaps/ and summary.json into
    JOB_DIR. Ground truth in the store is only used afterwards, for the ATE in the summary.
    The store's recommended border crop (the reference systems' for its camera; `bgs inspect`
    shows it) is applied unless --set crop_edge=N says otherwise.
    Checkpoints every `checkpoint_every` frames; SIGTERM/SIGUSR1/Ctrl-C checkpoint and exit 75,
    and running the same command again resumes. When the run is complete, its outputs are
    exported into JOB_DIR/outputs (once; `--no-export` skips this, `bgs export` redoes it).

    \b
    Example:
      bgs run fr1_rpy.h5 --job-dir jobs/fr1_rpy --preset cpu --set keyframes.mode=every
    """
    from bgs_batch.config import load_config, override_notes
    from bgs_batch.progress import progress_bar
    from jobs.preemption import stop_requests
    from jobs.run import run_job

    cfg = load_config(preset, list(overrides))
    for note in override_notes(cfg, list(overrides)):
        click.echo(f"Note: {note}", err=True)
    keyframes = []

    def on_start(frames: int) -> None:  # the store is open and valid
        advance(0, total=frames)

    def on_frame(event: dict) -> None:
        keyframes.append(event["keyframe"])
        loss = event.get("track_loss")
        status = f"{sum(keyframes)} keyframes" + (f", loss {loss:.3g}" if loss else "")
        advance(1, status)

    def on_visit(done: int, visits: int) -> None:  # the frames are done: the bar stays full
        advance(0, f"global map: {done}/{visits} steps")

    # from the run's start to the export's end a stop signal is noted, never the default death:
    # the run checkpoints on it, and one that comes after the run stops the export at its start
    with stop_requests():
        with progress_bar("SLAM", None, _show_progress(ctx)) as advance:
            summary = run_job(store, job_dir, cfg, max_frames=max_frames, force=force,
                              on_start=on_start, on_frame=on_frame, on_visit=on_visit)  # fmt: skip
        ate = "n/a (no GT)" if summary.ate_rmse_m is None else f"{summary.ate_rmse_m * 100:.2f} cm"
        click.echo(f"{summary.frames} frames, {summary.keyframes} keyframes, "
                   f"{summary.fps:.2f} fps, ATE RMSE {ate}; outputs in {job_dir}")  # fmt: skip
        if not no_export:
            _default_export(ctx, job_dir)


def _default_export(ctx: click.Context, job_dir: Path) -> None:
    """The end-of-run export, unless a complete one is newer than the run's summary; a stop
    signal noted since the run ended stops it at its start (exit 75: running the job again
    exports)."""
    from bgs_batch.errors import Interrupted
    from jobs.preemption import ExportStopped
    from outputs.export import RUN_DEFAULTS, export_is_current

    if export_is_current(job_dir):
        click.echo(f"outputs in {job_dir / 'outputs'} are up to date")
        return
    try:
        _run_export(ctx, job_dir, RUN_DEFAULTS, brief=True)  # the store recorded in job.json
    except Interrupted as err:  # e.g. Slurm's time-limit warning: exit 75 requeues the task
        raise ExportStopped(err.signum, job_dir) from err
    except BgsError as err:
        err.args = (f"the run finished, but its export failed: {err}; fix this and run "
                    f"`bgs export {job_dir}` (or pass --no-export)",)  # fmt: skip
        raise


@main.command()
@click.argument("prefix", required=False, default="")
@click.option("--preset", type=click.Choice(["cpu", "paper"]), default="cpu", show_default=True,
              help="Show the values of this preset.")  # fmt: skip
def settings(prefix: str, preset: str) -> None:
    """List the settings `bgs run --set KEY=VALUE` takes: each key with its value under the
    preset (and the other preset's, where it differs), what it accepts and what it does.

    PREFIX keeps the keys that start with it (a section such as `tracking`, or one key).

    \b
    Example:
      bgs settings tracking                 # the tracker's settings under the cpu preset
      bgs settings global_map.passes --preset paper
    """
    from bgs_batch.config import PRESETS, SETTINGS, accepted_values, load_config, override_notes

    keys = [key for key in SETTINGS if key.startswith(prefix)]
    if not keys:
        names = sorted({key.split(".")[0] for key in SETTINGS})
        raise click.BadParameter(f"no setting starts with {prefix!r}; the settings and sections "
                                 f"are {', '.join(names)}", param_hint="PREFIX")  # fmt: skip
    configs = {name: _flat_settings(load_config(name)) for name in PRESETS}
    for key in keys:
        value = configs[preset][key]
        others = [f"{name}: {_show(flat[key])}" for name, flat in configs.items()
                  if name != preset and flat[key] != value]  # fmt: skip
        click.echo(f"{key} = {_show(value)}" + (f" ({'; '.join(others)})" if others else "")
                   + f"  [{accepted_values(key)}]")  # fmt: skip
        click.echo(f"    {SETTINGS[key].metadata['doc']}")
        for note in override_notes(load_config(preset), [f"{key}="]):
            click.echo(f"    note: {note}")


def _flat_settings(config: Any) -> dict[str, Any]:
    """Every setting's value in `config`, by key."""
    from bgs_batch.config import SETTINGS

    flat = {}
    for key in SETTINGS:
        owner = config
        for part in key.split("."):
            owner = getattr(owner, part)
        flat[key] = owner
    return flat


def _show(value: Any) -> str:
    """A setting's value as `--set` takes it."""
    if value is None:
        return "none"
    return str(value).lower() if isinstance(value, bool) else str(value)


@main.command()
@click.argument("jobs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object per job.")
def status(jobs: tuple[Path, ...], as_json: bool) -> None:
    """Show the state of job directories: running, done, stopped, failed or new.

    Also frames processed, keyframes, frames per second and the last error. "stopped" is a job
    that checkpointed on a signal (exit 75): running it again resumes. Safe to call while a job
    runs. Folders that are not job directories are listed after the others, and the exit code
    is then 3.

    \b
    Example:
      bgs status jobs/*
    """
    from rich.console import Console
    from rich.table import Column, Table

    from bgs_batch.errors import InputError
    from jobs.status import job_status

    statuses, problems = [], []
    for job in jobs:
        try:
            statuses.append(job_status(job))
        except InputError as err:
            problems.append(err)
    if as_json:
        click.echo(json.dumps([s.as_dict() for s in statuses], indent=2))
    else:
        table = Table("job", Column("state", no_wrap=True), "frames", "keyframes", "fps",
                      "last error")  # fmt: skip
        colours = {"running": "cyan", "done": "green", "stopped": "yellow", "failed": "red",
                   "new": "white"}  # fmt: skip
        for s in statuses:
            fps = "-" if s.fps is None else f"{s.fps:.2f}"
            state = "stopped (resumable)" if s.state == "stopped" else s.state
            table.add_row(s.job, f"[{colours[s.state]}]{state}[/]", str(s.frames_done),
                          str(s.keyframes), fps, s.last_error or "")  # fmt: skip
        if statuses:
            Console().print(table)
        for s in statuses:
            for line in (s.readout, s.colour_offset):
                if line:
                    click.echo(f"{s.job}: {line}")
    for err in problems[:-1]:
        click.echo(f"Error: {err}", err=True)
    if problems:
        raise problems[-1]


@main.command()
@click.argument("stores", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--job-root", required=True, type=click.Path(path_type=Path),
              help="Folder holding one job directory per store (created).")
@click.option("--partition", help="Slurm partition.")
@click.option("--time", "time_limit", help="Slurm time limit per task, e.g. 24:00:00.")
@click.option("--cpus", default=2, show_default=True, type=click.IntRange(min=1),
              help="CPUs per task (also the run's thread count).")
@click.option("--preset", default="cpu", show_default=True, help="Settings preset of every run.")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
              help="Override a setting of every run (repeatable).")
@click.option("--dry-run", is_flag=True, help="Print the sbatch script instead of submitting.")
def submit(stores: tuple[Path, ...], job_root: Path, partition: str | None,
           time_limit: str | None, cpus: int, preset: str, overrides: tuple[str, ...],
           dry_run: bool) -> None:  # fmt: skip
    """Submit one Slurm array job that runs SLAM on every STORE (one task each).

    Tasks get SIGUSR1 two minutes before their time limit (and SIGTERM on pre-emption),
    checkpoint, requeue themselves and resume where they stopped. Follow them with
    `bgs status JOB_ROOT/*`.

    \b
    Example:
      bgs submit stores/*.h5 --job-root runs --partition cpu --time 12:00:00 --cpus 4
      bgs submit fr1_rpy.h5 --job-root runs --dry-run
    """
    from bgs_batch.config import load_config
    from jobs.slurm import SubmitOptions, sbatch_script
    from jobs.slurm import submit as sbatch_submit

    load_config(preset, list(overrides))  # refuse bad settings before anything is submitted
    options = SubmitOptions(partition, time_limit, cpus, preset, overrides)
    script = sbatch_script(list(stores), job_root, options)
    if dry_run:
        click.echo(script, nl=False)
        return
    job_root.mkdir(parents=True, exist_ok=True)
    job_id = sbatch_submit(script)
    click.echo(f"submitted array job {job_id} with {len(stores)} task(s); "
               f"follow it with: bgs status {job_root}/*")  # fmt: skip
