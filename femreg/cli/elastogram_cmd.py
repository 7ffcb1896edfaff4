"""``femreg elastogram FRAMES -o OUT/``: a freehand cine loop -> the pairs worth registering -> a persistent strain
cine and one best elastogram (:func:`femreg.elastogram.elastogram`).

Writes ``OUT/pairs.csv`` (one row per candidate pair: ref, mov, axial_strain_percent, ncc, quality, selected),
``OUT/elastogram.npz`` (``exx`` normalised axial strain on the grid of frame ``ref_frame``, NaN where not covered;
``quality``, ``spacing``, ``origin``; ``region``: the rows and lines of the input frames registered, for RF
frames' echo rectangle (as ``femreg register``), a ``--roi`` / ``--depth`` or a scan-converted fan's bounding box,
and ``excluded``: what was left out and why (the pictures hatch it); ``data_mask`` for a fan: on ``region``, True in the
fan, outside which every picture is empty),
``OUT/elastogram.png`` (B-mode | elastogram | quality) and
``OUT/strain_cine.mp4`` (imageio-ffmpeg; ``strain_cine.gif`` when it is not installed).  Per-pair results are in
``OUT/pairs/`` as soon as they are computed; ``--resume`` keeps them.

``--geometry convex|sector`` (``--radius``, ``--angle-pitch``): frames (samples, rays) of a convex or phased
array, each pair registered in physical x, y (:func:`femreg.geometry.register_beam`); ``exx``, ``quality`` and the
pictures are scan-converted onto a Cartesian grid (``spacing``, ``origin`` in mm, ``data_mask`` the fan; the npz
also names the probe: ``geometry_kind``, ``geometry_radius_mm``, ``geometry_angle_pitch_deg``).  Only the range
step of the spacing is read (``--spacing DX auto``); the first range is ``--origin``, else the file's, else the
start depth its header states.

Exit codes: 0 done, 1 computed but no pair usable, or the computation failed, 2 bad input (before any work).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from ..errors import InputError, counted
from ._common import (add_reader_args, add_registration_args, beam_frames_from_args, file_frame, frames_from_args,
                      ncc_arg, registration_kwargs)
from .register_cmd import (_check_stated_geometry, _geometry, _refuse_curved, add_geometry_args, beam_start_range,
                           refuse_unused_geometry)


def add_parser(subparsers):
    p = subparsers.add_parser(
        "elastogram", help="freehand cine loop -> strain cine and best elastogram",
        description="Screen every consecutive pair of FRAMES on decimated envelopes, choose pairs whose axial "
                    "strain lies in the band with little lateral and out-of-plane motion, register them, "
                    "normalise each strain image by its mean and combine them by quality-weighted persistence.")
    p.add_argument("file", help="RF or B-mode frames (npy, npz, mat, mhd, raw, Clarius raw, .rf, .uff/.h5, DICOM .dcm, "
                                "or a folder of per-frame files)")
    p.add_argument("-o", "--output", required=True, metavar="OUTDIR", help="output folder")
    p.add_argument("--band", nargs=2, type=float, metavar=("LO", "HI"), default=(0.5, 2.0),
                   help="axial strain magnitude of the pairs to register, percent (default 0.5 2)")
    p.add_argument("--min-ncc", type=ncc_arg, default=0.6, help="least envelope NCC of a pair (default 0.6)")
    p.add_argument("--max-span", type=int, default=8, help="largest frame distance of a pair (default 8)")
    p.add_argument("--max-lateral", type=float, metavar="MM",
                   help="largest lateral motion within a pair, mm (default a tenth of the image width)")
    p.add_argument("--persistence", type=float, default=0.7, help="persistence factor in [0, 1) (default 0.7)")
    p.add_argument("--strain-range", nargs=2, type=float, metavar=("LO", "HI"),
                   help="colour range of the normalised strain (1 = the mean) in elastogram.png and the cine "
                        "(default: its 2-98 %% percentiles over the pixels of at least median quality, "
                        "femreg.elastogram.display_range; e.g. 0 2 to compare loops on one fixed scale)")
    p.add_argument("--fps", type=float, default=10.0, help="frame rate of the strain cine (default 10)")
    p.add_argument("--resume", action="store_true", help="continue a run in OUTDIR, keeping finished pairs")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--workers", type=int, default=1, metavar="N",
                   help="local worker processes for the screening and the registrations (default 1: this "
                        "process; on 2 free cores, 2 workers register every consecutive pair at 24 instead of 19 "
                        "frames/s, and gain nothing when one pair in four is registered)")
    add_geometry_args(p, choices=("linear", "convex", "sector"))
    add_registration_args(p)
    add_reader_args(p)
    p.set_defaults(func=run)
    return p


#: A --band whose top is at most this (percent) is fractions typed as percent: freehand pairs strain 0.1-10 %.
MIN_BAND_TOP = 0.05


def _display(img, spacing, height=320, average=False):
    """Resampling to square display pixels, ``height`` rows: nearest neighbour, or with ``average`` the mean of
    the samples each display pixel covers along an axis that is reduced (a B-mode: picking one of several
    samples per pixel aliases the speckle into salt-and-pepper noise)."""
    ext = np.asarray(img.shape) * np.asarray(spacing, float)
    width = max(2, int(round(height * ext[1] / ext[0])))
    out = np.asarray(img)
    for axis, n in ((0, height), (1, width)):
        m = out.shape[axis]
        if average and m > n:
            edges = np.round(np.arange(n + 1) * m / n).astype(int)
            out = np.add.reduceat(out, edges[:-1], axis=axis) / np.diff(edges).reshape(
                (-1, 1) if axis == 0 else (1, -1))
        else:
            idx = np.minimum((np.arange(n) + 0.5) * m / n, m - 1).astype(int)
            out = np.take(out, idx, axis=axis)
    return out


def on_frames(res, shape, spacing, origin):
    """``(view, outside, roi, row0)``: a result cut to a rectangle of the input frames (``res.region``: the echo
    rectangle of :func:`femreg.echo.find_echo`, a given ``--roi`` / ``--depth``) put back on the frames
    (``shape`` (n_axial, n_lateral), ``spacing``, ``origin`` mm) for the pictures: ``view`` a copy whose
    ``exx`` / ``cine`` are NaN and ``quality`` 0 outside the rectangle, ``outside`` (bool, ``view.exx``'s shape)
    those pixels and the rectangle's own pixels without strain (the mesh's margin), ``roi`` (x0, x1, y0, y1) mm the
    rectangle, ``row0`` the first input row of ``view``'s grid
    (fewer than the cine's row step: its rows stay on the cine's).  None for a whole-frame, fan or convex /
    sector result (its pictures keep its own grid)."""
    import dataclasses

    if res.region is None or res.data_mask is not None or getattr(res, "geometry", None) is not None:
        return None
    (a, b), (c, d) = res.region
    n, m = (int(v) for v in shape)
    dx, dy = (float(v) for v in spacing)
    qa = max(1, int(round(float(res.cine_spacing[0]) / dx))) if res.cine_spacing is not None else 1
    a0 = a % qa
    nv = n - a0
    exx, quality = np.full((nv, m), np.nan), np.zeros((nv, m))
    exx[a - a0:b - a0, c:d], quality[a - a0:b - a0, c:d] = res.exx, res.quality
    cine = np.full((len(res.cine), len(range(0, nv, qa)), m), np.nan, np.float32)
    k0 = (a - a0) // qa
    cine[:, k0:k0 + res.cine.shape[1], c:d] = res.cine
    outside = np.ones((nv, m), bool)
    outside[a - a0:b - a0, c:d] = False
    outside |= ~np.isfinite(exx)        # the mesh's own margin inside the rectangle: no strain there either
    ox = float(origin[0]) + a0 * dx
    roi = (ox + (a - a0 - 0.5) * dx, ox + (b - a0 - 0.5) * dx, float(origin[1]) + (c - 0.5) * dy,
           float(origin[1]) + (d - 0.5) * dy)
    view = dataclasses.replace(res, exx=exx, quality=quality, cine=cine, origin=np.array([ox, float(origin[1])]),
                               spacing=np.array([dx, dy]), region=None)
    return view, outside, roi, a0


def _hatch(axs, outside, spacing, origin, roi):
    """Hatch ``outside`` (left out of the mesh) on every panel of ``axs`` and outline ``roi``."""
    from ..plot import _shade_outside

    for ax in axs:
        _shade_outside(ax, outside, spacing, origin, roi)


#: Label of the normalised strain's colour bar (elastogram.png and the cine): its unit is the image's mean.
STRAIN_LABEL = "axial strain / its mean (1 = mean; bright = soft)"
#: Height of the strain cine's frames, inches at :data:`CINE_DPI`.
CINE_HEIGHT_IN, CINE_DPI = 4.6, 90


def _cine_bmode(res, frame, spacing):
    """The B-mode (dB) of ``frame`` (the input frame cut to ``res.region``) on the grid of ``res.exx``: averaged
    to about :data:`CINE_HEIGHT_IN` x 100 rows (picking one of several samples per display pixel aliases the
    speckle into salt-and-pepper noise) with its spacing (mm); a convex / sector frame's scan-converted (NaN
    outside the fan)."""
    from ..plot import bmode

    b = bmode(np.asarray(frame, float))
    if getattr(res, "geometry", None) is not None:
        b = res.to_grid(b)
        return b, np.asarray(res.spacing, float)
    rows = max(2, int(CINE_HEIGHT_IN * 100))
    out = _display(b, spacing, height=min(rows, b.shape[0]), average=True)
    return out, np.asarray(spacing, float) * np.asarray(b.shape) / np.asarray(out.shape)


def cine_figure(res, bmode_db, bmode_spacing, strain, strain_range, title="", dynamic_range=50.0, outside=None,
                roi=None):
    """The strain cine's figure for one frame: the B-mode ``bmode_db`` (dB, on ``bmode_spacing`` mm from
    ``res.origin``) | the normalised strain ``strain`` (on ``res.cine_spacing``; viridis over ``strain_range``),
    both on mm axes (axial x, lateral y) with their colour bars (echo level dB; the strain over its mean),
    ``title`` above; ``outside`` (bool, on ``res.exx``'s grid) hatched on both, ``roi`` (x0, x1, y0, y1) mm
    outlined (:func:`on_frames`).  Returns ``(fig, (ax_bmode, ax_strain))``."""
    import matplotlib.pyplot as plt

    from ..plot import extent_mm, fit_colorbars, plot_field

    lo, hi = strain_range
    ext = np.asarray(res.exx.shape) * np.asarray(res.spacing, float)        # mm, axial and lateral
    aspect = float(np.clip(ext[1] / max(ext[0], 1e-9), 0.25, 3.0))
    fig, axs = plt.subplots(1, 2, figsize=(2 * aspect * (CINE_HEIGHT_IN - 1.0) + 3.4, CINE_HEIGHT_IN),
                            dpi=CINE_DPI, constrained_layout=True)
    # the B-mode resampled to display pixels (_cine_bmode) covers the frame's pixels: its first pixel centre lies
    # half a display pixel inside the frame's edge, not on the frame's first pixel centre
    b_origin = np.asarray(res.origin, float) + (np.asarray(bmode_spacing, float) - np.asarray(res.spacing, float)) / 2
    plot_field(bmode_db, bmode_spacing, b_origin, ax=axs[0], cmap="gray", vmin=-dynamic_range, vmax=0.0,
               label="echo level (dB)", title="B-mode")
    plot_field(strain, res.cine_spacing, res.origin, ax=axs[1], cmap="viridis", vmin=lo, vmax=hi,
               label=STRAIN_LABEL, title="normalised axial strain")
    for ax in axs:
        ax.set_facecolor("black")       # outside a fan and where no pair covers
    if outside is not None:
        _hatch(axs, outside, res.spacing, res.origin, roi)
    # both panels on the frame's pixels: an outline on the frame's edge just outside an image's would otherwise
    # add autoscale's 5 % margin on that side, a black strip (1.3 mm on a 25.6 mm wide frame)
    left, right, bottom, top = extent_mm(res.exx.shape, res.spacing, res.origin)
    for ax in axs:
        ax.set_xlim(left, right)
        ax.set_ylim(bottom, top)
    fig.suptitle(title)
    fit_colorbars(fig, [list(axs)])
    return fig, tuple(axs)


def cine_frames(res, frames, spacing, strain_range=None, dynamic_range=50.0, outside=None, roi=None):
    """The frames of the strain cine, each (height, width, 3) uint8: :func:`cine_figure` of every cine frame,
    the B-mode of its reference frame beside the persistent normalised strain after its pair (colours over
    ``strain_range``, default :func:`femreg.elastogram.display_range`, as ``elastogram.png``), titled with the
    frame and its pair's mean axial strain (%).  A convex / sector loop is drawn scan-converted
    (``res.geometry``); ``outside`` / ``roi`` hatched (:func:`cine_figure`).  One figure is drawn and its images
    replaced frame by frame."""
    import matplotlib.pyplot as plt

    from ..elastogram import display_range

    rng = tuple(strain_range) if strain_range is not None else display_range(res.exx, res.quality)
    pair_of = {int(p["ref"]): (int(p["mov"]), 100.0 * float(p["strain"])) for p in res.pairs if p["usable"]}
    pics, fig = [], None
    try:
        for k, f in enumerate(res.cine_frames):
            b, bsp = _cine_bmode(res, frames[f], spacing)
            s = np.asarray(res.cine[k], float)
            what = f"frame {f}" + (f" (pair {f} -> {pair_of[f][0]}, mean axial strain {pair_of[f][1]:+.2f} %)"
                                   if f in pair_of else "")
            if fig is None:
                fig, axs = cine_figure(res, b, bsp, s, rng, what, dynamic_range, outside, roi)
                drawn = [axs[0].images[-1], axs[1].images[-1]]
                # the axes, colour bars and labels drawn once, without the images and the title: each frame then
                # draws only those on that background (a whole draw took 0.23 s a frame)
                fig.canvas.draw()           # the layout, with the title in its place
                fig.set_layout_engine("none")
                for a in drawn + [fig._suptitle]:
                    a.set_visible(False)
                fig.canvas.draw()
                background = fig.canvas.copy_from_bbox(fig.bbox)
                for a in drawn + [fig._suptitle]:
                    a.set_visible(True)
            else:
                drawn[0].set_data(np.ma.masked_invalid(b))
                drawn[1].set_data(np.ma.masked_invalid(s))
                fig._suptitle.set_text(what)
            fig.canvas.restore_region(background)
            for ax, im in zip(axs, drawn):
                ax.draw_artist(im)
                for a in ax.collections + ax.patches:   # the hatching over what was left out
                    ax.draw_artist(a)
                for spine in ax.spines.values():    # the frame over the image's edge, as a whole draw has it
                    ax.draw_artist(spine)
            fig.draw_artist(fig._suptitle)
            pic = np.asarray(fig.canvas.buffer_rgba())[..., :3]
            h, w = (-(-pic.shape[0] // 16) * 16, -(-pic.shape[1] // 16) * 16)   # codec macro blocks
            pad = np.full((h, w, 3), 255, np.uint8)
            pad[:pic.shape[0], :pic.shape[1]] = pic
            pics.append(pad)
    finally:
        if fig is not None:
            plt.close(fig)
    return pics


def write_cine(out_dir, res, frames, spacing, fps=10.0, strain_range=None, outside=None, roi=None) -> Path:
    """The strain cine of :func:`cine_frames`: ``strain_cine.mp4`` with imageio-ffmpeg, else a GIF."""
    pics = cine_frames(res, frames, spacing, strain_range, outside=outside, roi=roi)
    try:
        import imageio_ffmpeg
    except ImportError:
        imageio_ffmpeg = None
    if imageio_ffmpeg is not None and pics:
        path = Path(out_dir) / "strain_cine.mp4"
        tmp = path.with_name(".strain_cine.tmp.mp4")
        w = imageio_ffmpeg.write_frames(str(tmp), (pics[0].shape[1], pics[0].shape[0]), fps=fps,
                                        macro_block_size=16, quality=7)
        w.send(None)
        for p in pics:
            w.send(np.ascontiguousarray(p))
        w.close()
        tmp.replace(path)
        return path
    from PIL import Image

    path = Path(out_dir) / "strain_cine.gif"
    tmp = path.with_name(".strain_cine.tmp.gif")
    ims = [Image.fromarray(p) for p in pics] or [Image.new("RGB", (16, 16))]
    ims[0].save(tmp, save_all=True, append_images=ims[1:], duration=int(1000 / fps), loop=0)
    tmp.replace(path)
    return path


def elastogram_figure(res, frame, spacing, origin, strain_range=None, failure=None, outside=None, roi=None,
                      excluded=None):
    """The figure of ``elastogram.png``: B-mode of the reference frame | best elastogram (colours over
    ``strain_range``, default :func:`femreg.elastogram.display_range`) | its persistence weight, each colour bar
    clear of the next panel's axis label.  ``failure``: the reason no pair was usable, drawn as the red banner
    of a failed result (:func:`femreg.plot.draw_failure`) over the empty panels.  ``outside`` (bool, on
    ``res.exx``'s grid): pixels left out of the mesh, hatched on every panel with ``roi`` (x0, x1, y0, y1) mm
    outlined and ``excluded`` (why) written below the panels (:func:`on_frames`)."""
    import matplotlib.pyplot as plt

    from ..elastogram import display_range, saturated_fraction
    from ..plot import draw_failure, extent_mm, fit_colorbars, plot_bmode, plot_field, span_note

    lo, hi = strain_range if strain_range is not None else display_range(res.exx, res.quality)

    height = 5.0
    if getattr(res, "geometry", None) is not None:
        # a fan is wider than deep: the figure as tall as its panels need (a fixed 5 in left 40 % of it white)
        e = extent_mm(res.exx.shape, res.spacing, res.origin)
        height = float(np.clip(3.2 * abs(e[2] - e[3]) / max(abs(e[1] - e[0]), 1e-9) + 1.9, 3.2, 7.0))
    fig, axs = plt.subplots(1, 3, figsize=(13, height), constrained_layout=True)
    title = f"B-mode, frame index {res.ref_frame}"
    if getattr(res, "geometry", None) is not None:      # the (range, angle) frame at its samples' positions
        pos = res.geometry.sample_positions(np.shape(frame), res.sample_spacing, res.sample_origin)
        plot_bmode(frame, res.sample_spacing, res.sample_origin, ax=axs[0], title=title, positions=pos)
        ext = extent_mm(res.exx.shape, res.spacing, res.origin)
        axs[0].set_xlim(ext[0], ext[1])
        axs[0].set_ylim(ext[2], ext[3])
    else:
        plot_bmode(frame, spacing, origin, ax=axs[0], title=title)
    pairs = f"{res.n_usable} pair" + ("" if res.n_usable == 1 else "s")
    # the share drawn in an end colour: the picture says how much of it the colour bar does not resolve
    sat = saturated_fraction(res.exx, res.quality, (lo, hi))
    beyond = f"\n{100 * sat:.1f} % of the pixels beyond the colour bar" if np.isfinite(sat) else ""
    # full-scale colours over a few percent read as strong contrast (a 15 MHz loop: 0.975-1.03 drawn as a stiff
    # column under a soft blob, where the nodule's truth spans 0.4-1.24); the strain is normalised: mean 1
    beyond += span_note(lo, hi, 1.0)
    plot_field(res.exx, spacing, origin, ax=axs[1], title=f"normalised axial strain ({pairs}){beyond}",
               cmap="viridis", vmin=lo, vmax=hi, label=STRAIN_LABEL)
    q = np.where(res.quality > 0, res.quality, np.nan)
    med = float(np.nanmedian(q)) if np.isfinite(q).any() else 1.0
    # relative to the median on a log scale over its 2-98 % percentiles: the weight spans 20x and more (static
    # near-field echoes, NCC ~1), which a linear 0-3x range saturated on a quarter of the in vivo pixels
    lq = np.log10(q / med)
    qlo, qhi = np.nanpercentile(lq, [2.0, 98.0]) if np.isfinite(lq).any() else (-1.0, 1.0)
    qlo, qhi = min(qlo, -0.1), max(qhi, 0.1)
    plot_field(lq, spacing, origin, ax=axs[2], title="quality (persistence weight)", cmap="magma", vmin=qlo,
               vmax=qhi, label="persistence weight / its median (log scale)")
    cb = axs[2].images[-1].colorbar
    if cb is not None:
        ticks = [v for v in (0.01, 0.03, 0.1, 0.3, 1, 3, 10, 30, 100) if qlo <= np.log10(v) <= qhi]
        cb.set_ticks(np.log10(ticks), labels=[f"{v:g}" for v in ticks])
    for ax in axs:
        ax.set_xlabel("lateral y (mm)")
        ax.set_ylabel("axial x (mm)")
    if outside is not None and outside.any():
        import textwrap

        from ..plot import SUPXLABEL_WIDTH

        _hatch(axs, outside, spacing, origin, roi)         # why: below the panels (a narrow panel cuts it)
        fig.supxlabel(textwrap.fill("hatched: left out of the mesh (no strain there)"
                                    + (f"; {excluded}" if excluded else ""), SUPXLABEL_WIDTH), fontsize="small")
    elif excluded:                  # the loop cut before the registration (a fan's ranges past the echo): not drawn
        import textwrap

        from ..plot import SUPXLABEL_WIDTH

        fig.supxlabel(textwrap.fill(f"not shown: {excluded}", SUPXLABEL_WIDTH), fontsize="small")
    if failure:
        # the whole advice: the band to pass is at its end
        draw_failure(fig, f"NO ELASTOGRAM: {failure}", max_lines=None)
        for ax in axs[1:]:
            ax.text(0.5, 0.5, "no usable pair", transform=ax.transAxes, ha="center", va="center", color="0.4")
    fit_colorbars(fig, [list(axs)])
    if failure:
        for ax in axs[1:]:
            cb = ax.images[-1].colorbar if ax.images else None
            if cb is not None:          # a scale over no data would read as a measured range
                cb.ax.set_visible(False)
    return fig


def write_picture(path, res, frame, spacing, origin, strain_range=None, failure=None, **hatch) -> None:
    """Write :func:`elastogram_figure` to ``path`` (PNG, written under a temporary name and renamed); ``hatch``:
    its ``outside``, ``roi``, ``excluded``."""
    import matplotlib.pyplot as plt

    fig = elastogram_figure(res, frame, spacing, origin, strain_range, failure, **hatch)
    tmp = Path(path).with_name(".elastogram.tmp.png")
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    tmp.replace(path)


def run(args) -> int:
    from .._atomic import atomic_savez
    from ..elastogram import band_advice, elastogram, write_pairs_csv

    lo, hi = args.band
    if not 0 < lo < hi < 20:            # the flags are in percent (the function's band in fractions)
        raise InputError(f"--band LO HI must satisfy 0 < LO < HI < 20 (percent of axial strain), got {lo:g} {hi:g}")
    if hi <= MIN_BAND_TOP:              # 0.005 0.02: fractions typed where percent are asked
        raise InputError(f"--band {lo:g} {hi:g} is in percent: a band up to {hi:g} % of axial strain is below what "
                         f"elastography registers (0.1-10 %); as fractions it is --band {lo * 100:g} {hi * 100:g}")
    if args.strain_range is not None and not (np.all(np.isfinite(args.strain_range))
                                              and args.strain_range[0] < args.strain_range[1]):
        raise InputError("--strain-range LO HI must be finite with LO < HI (normalised strain, 1 = the mean), got "
                         f"{args.strain_range[0]:g} {args.strain_range[1]:g}")
    if not (0 < args.fps < float("inf")):
        raise InputError(f"--fps must be a number > 0 (frames per second of the strain cine), got {args.fps:g}")
    refuse_unused_geometry(args)
    from ._common import volumes_only

    if volumes_only(Path(args.file)):          # before its spacing is asked for: it would not be used
        raise InputError(f"{args.file} holds RF volumes (4D data or three spacing values): femreg elastogram takes "
                         "a loop of frames; femreg track registers a volume loop")
    beam = None
    if args.geometry in ("convex", "sector"):   # frames along rays: range step and first range from the file
        from ..geometry import sample_space

        beam = _geometry(args)
        fr, dr, _ = beam_frames_from_args(args, beam)
        _check_stated_geometry(fr, args.file, beam, args)
        spacing, origin = dr, (beam_start_range(fr, args.file, args), 0.0)
        mesh_spacing = sample_space(beam, fr.shape, dr, origin[0])[1]   # the frames as linear images (mm)
    else:
        fr = frames_from_args(args)
        if not args.no_orientation_check and not getattr(args, "geometry_given", False):
            _refuse_curved(fr, args.file)
        spacing, origin, mesh_spacing = fr.spacing, fr.origin, fr.spacing
    kw = registration_kwargs(args)
    out = Path(args.output)

    from ..progress import stderr_is_terminal

    start, said = time.monotonic(), []
    as_progress = not args.no_progress and not stderr_is_terminal()

    def on_pair(r):
        said.append(r)
        # off a terminal this line is the progress (no register bar): the count and elapsed time with it
        count = f" ({len(said)} registered, {time.monotonic() - start:.1f} s)" if as_progress else ""
        line = (f"pair {r['ref']:4d} -> {r['mov']:4d}: strain {100 * r['strain']:+.2f} %{count}"
                + ("" if r["usable"] else f"  REJECTED: {r['message']}"))
        print(line, file=sys.stdout if args.no_progress else sys.stderr)

    on_pair.reports_progress = True

    if fr.n_frames < 3:
        raise InputError(f"{args.file}: need at least 3 frames for an elastogram, got {fr.n_frames}")
    from ..mesh import check_element_size

    check_element_size(kw.get("element_size"), mesh_spacing)    # before the screening writes anything
    try:
        res = elastogram(fr.frames, spacing=spacing, origin=origin, band=(lo / 100.0, hi / 100.0),
                         min_ncc=args.min_ncc, max_span=args.max_span, max_lateral_mm=args.max_lateral,
                         persistence=args.persistence, output_dir=out, resume=args.resume,
                         progress=not args.no_progress, on_pair=on_pair, workers=args.workers, geometry=beam, **kw)
    except InputError:
        raise                   # bad input: exit 2 from the dispatcher
    except Exception as exc:  # noqa: BLE001 - a computation that fails is exit 1, finished pairs kept
        msg = " ".join(str(exc).split()) or type(exc).__name__
        print(f"femreg elastogram: failed: the elastogram could not be computed ({type(exc).__name__}: {msg}); "
              f"finished pairs are kept in {out / 'pairs'} (--resume continues)", file=sys.stderr)
        return 1
    write_pairs_csv(out / "pairs.csv", res.pairs)
    fan = {} if res.data_mask is None else dict(data_mask=res.data_mask)
    if res.region is not None:      # the echo rectangle, a fan's bounding box or a given --roi / --depth
        fan["region"] = np.asarray(res.region, np.int64)
    if res.excluded:
        fan["excluded"] = np.str_(res.excluded)
    from ..elastogram import display_range

    shown = tuple(args.strain_range) if args.strain_range is not None else display_range(res.exx, res.quality)
    if beam is not None:        # the probe whose (range, angle) frames exx was scan-converted from
        fan.update(geometry_kind=np.array(beam.kind), geometry_radius_mm=np.array(float(beam.radius_mm)),
                   geometry_angle_pitch_deg=np.array(float(beam.angle_pitch_deg)),
                   sample_origin=np.asarray(res.sample_origin, float))
    atomic_savez(out / "elastogram.npz", exx=res.exx, ref_frame=np.int64(res.ref_frame), quality=res.quality,
                 spacing=np.asarray(res.spacing), origin=np.asarray(res.origin),
                 strain_range=np.asarray(shown, float), **fan)
    frames, shown_res, hatch = fr.frames, res, {}
    if res.excluded:
        print(f"femreg elastogram: left out of the mesh (the rest is registered): {res.excluded}")
    put = on_frames(res, np.shape(fr.frames[0]), spacing, origin)
    if put is not None:             # a rectangle of the frames: the pictures on the whole frames, the rest hatched
        shown_res, outside, roi, a0 = put
        frames = [np.asarray(f)[a0:] for f in frames]
        hatch = dict(outside=outside, roi=roi)
    elif res.region is not None:    # the fan's bounding box (NaN outside the fan): its pixels
        (a, b), (c, d) = res.region
        frames = [np.asarray(f)[a:b, c:d] for f in frames]
    failure = None
    if res.n_usable == 0:
        why = band_advice(res.screen, (lo / 100.0, hi / 100.0), args.max_span, cli=True)
        failure = (f"no pair was usable (none with strain in {lo:g}-{hi:g} % that registered; see "
                   f"{out / 'pairs.csv'})" + (f": {why}" if why else ""))
    write_picture(out / "elastogram.png", shown_res, np.asarray(frames[res.ref_frame], float), shown_res.spacing,
                  shown_res.origin, shown, failure,
                  excluded=res.excluded if hatch or getattr(res, "geometry", None) is not None else None, **hatch)
    cine = write_cine(out, shown_res, frames, shown_res.spacing, fps=args.fps, strain_range=shown, **hatch)
    n_sel = sum(1 for p in res.pairs if p["registered"])
    files = (getattr(fr, "metadata", None) or {}).get("files")   # a folder of frame files: name the file too
    which = f" ({files[res.ref_frame]})" if files and len(files) == fr.n_frames else ""
    sel = getattr(args, "frames", None)
    moved = sel is not None and any(file_frame(sel, k) != k for k in range(fr.n_frames))
    if moved:               # a --frames selection counts its own frames from 0, as pairs.csv does
        which = f" (the file's frame {file_frame(sel, res.ref_frame)})"
    print(f"femreg elastogram: {fr.n_frames} frames, {counted(len(res.pairs), 'candidate pair')}, {n_sel} registered, "
          f"{res.n_usable} usable; "
          + (f"best elastogram on frame index {res.ref_frame}{which}; " if res.n_usable else
             "no elastogram (empty strain panels); ")
          + f"wrote {out / 'elastogram.npz'}, elastogram.png, {cine.name}, pairs.csv"
          + (" and the registered pairs in pairs/" if n_sel else "") + f" ({res.timings['total']:.1f} s)")
    if res.repeated:        # frames written twice: a loop that holds fewer distinct frames than it seems
        from ..image import repeats_listed

        shown = repeats_listed(res.repeated)
        verb = "repeats" if len(res.repeated) == 1 else "repeat"
        merged = sum(1 for k in res.repeated if k < fr.n_frames - 1)     # the last frame starts no pair
        print(f"femreg elastogram: note: {len(res.repeated)} of {fr.n_frames} frames {verb} the one before "
              f"(identical samples; frames {shown}): no motion between them, pairs ending on one are the pairs "
              "ending on the frame before"
              + (f"; {merged} candidate pair{'s' if merged != 1 else ''} starting on one merged into the pair "
                 "starting on the frame before (not listed in pairs.csv)" if merged else ""))
    if moved:
        print(f"femreg elastogram: note: --frames selected the file's frames "
              f"{', '.join(str(file_frame(sel, k)) for k in range(fr.n_frames))}: the frame indices here and in "
              "pairs.csv count the selection from 0")
    if failure:
        print(f"femreg elastogram: failed: {failure}", file=sys.stderr)
        return 1
    return 0
