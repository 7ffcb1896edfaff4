"""DICOM ultrasound images and cine loops (femreg.io.dicom): region crop, spacing cm -> mm and its axes, colour to
luma, folders by InstanceNumber, the DICM marker without an extension, the refusals (no calibration, units, colour
Doppler, a contradicting --spacing, a compressed file without its decoder), femreg info, and a B-mode pair written
as DICOM registered to its known strain through the CLI."""
from __future__ import annotations

import json
import sys

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")

from pydicom.dataset import Dataset, FileMetaDataset  # noqa: E402
from pydicom.sequence import Sequence  # noqa: E402
from pydicom.uid import ExplicitVRLittleEndian, generate_uid  # noqa: E402

from femreg.cli import main  # noqa: E402
from femreg.errors import FileFormatError, InputError  # noqa: E402
from femreg.io import detect_format, read_frames  # noqa: E402

US_MULTIFRAME = "1.2.840.10008.5.1.4.1.1.3.1"       # Ultrasound Multi-frame Image Storage
SERIES = generate_uid()


def region(x0=60, y0=40, x1=259, y1=199, dx_cm=0.012, dy_cm=0.01, data_type=1, units=(3, 3), ref=None):
    """One SequenceOfUltrasoundRegions item; ``ref`` = (x0, y0, value x cm, value y cm) of the reference pixel."""
    r = Dataset()
    r.RegionSpatialFormat = 1
    r.RegionDataType = data_type
    r.RegionFlags = 0
    r.RegionLocationMinX0, r.RegionLocationMinY0, r.RegionLocationMaxX1, r.RegionLocationMaxY1 = x0, y0, x1, y1
    r.PhysicalUnitsXDirection, r.PhysicalUnitsYDirection = units
    r.PhysicalDeltaX, r.PhysicalDeltaY = dx_cm, dy_cm
    if ref is not None:
        r.ReferencePixelX0, r.ReferencePixelY0, r.ReferencePixelPhysicalValueX, r.ReferencePixelPhysicalValueY = ref
    return r


def write_dicom(path, frames, regions=(), *, photometric=None, frame_time=None, instance=None, series=SERIES,
                preamble=True):
    """A DICOM file of ``frames`` (n, rows, cols) grey or (n, rows, cols, 3) RGB uint8, as a scanner exports it."""
    frames = np.asarray(frames, np.uint8)
    rgb = frames.ndim == 4
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta.MediaStorageSOPClassUID = US_MULTIFRAME
    ds.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    ds.SOPClassUID, ds.SOPInstanceUID = US_MULTIFRAME, ds.file_meta.MediaStorageSOPInstanceUID
    ds.Modality, ds.Manufacturer, ds.SeriesInstanceUID = "US", "Clinic", series
    if instance is not None:
        ds.InstanceNumber = instance
    ds.Rows, ds.Columns = frames.shape[1:3]
    ds.SamplesPerPixel = 3 if rgb else 1
    ds.PhotometricInterpretation = photometric or ("RGB" if rgb else "MONOCHROME2")
    if rgb:
        ds.PlanarConfiguration = 0
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 8, 8, 7, 0
    ds.NumberOfFrames = frames.shape[0]
    if frame_time is not None:
        ds.FrameTime = frame_time
    if regions:
        ds.SequenceOfUltrasoundRegions = Sequence(list(regions))
    ds.PixelData = frames.tobytes()
    ds.save_as(path, enforce_file_format=preamble)
    return path


def screen(tissue, rows=240, cols=320, x0=60, y0=40, seed=0):
    """Frames of a scanner's screen: ``tissue`` (n, h, w) grey placed at (y0, x0) of an RGB canvas with coloured
    burned-in text around it."""
    tissue = np.asarray(tissue, np.uint8)
    n, h, w = tissue.shape
    out = np.zeros((n, rows, cols, 3), np.uint8)
    out[:, y0:y0 + h, x0:x0 + w] = tissue[..., None]
    rng = np.random.default_rng(seed)
    out[:, 5:25, 5:150] = rng.integers(0, 256, (20, 145, 3))         # patient name, coloured
    out[:, 210:235, 270:315] = (255, 200, 0)                         # a yellow logo
    return out


@pytest.fixture
def loop(tmp_path):
    rng = np.random.default_rng(1)
    tissue = rng.integers(0, 256, (4, 160, 200)).astype(np.uint8)
    path = write_dicom(tmp_path / "IM_0001.dcm", screen(tissue), [region()], frame_time=40.0)
    return path, tissue


def test_multiframe_rgb_crop_spacing_and_frame_rate(loop):
    path, tissue = loop
    fr = read_frames(path)
    assert fr.frames.shape == (4, 160, 200) and fr.format == "dicom"
    # rows are depth: PhysicalDeltaY 0.01 cm -> 0.1 mm axial; columns lateral: 0.012 cm -> 0.12 mm
    assert fr.spacing == pytest.approx((0.1, 0.12), rel=1e-12)
    assert fr.origin == (0.0, 0.0)
    # grey RGB pixels keep their value (BT.601 weights sum to 1); the burned-in text is cropped away
    np.testing.assert_allclose(fr.frames, tissue, atol=1e-3)
    assert fr.metadata["frame_rate"] == pytest.approx(25.0) and "FrameTime 40 ms" in fr.metadata["frame_rate_source"]
    assert fr.metadata["region"]["rows"] == [40, 199] and fr.metadata["region"]["columns"] == [60, 259]
    assert "BT.601" in fr.metadata["colour"]
    two = read_frames(path, frames=[3, 1])
    np.testing.assert_allclose(two.frames, tissue[[3, 1]], atol=1e-3)
    with pytest.raises(InputError, match="does not write it"):
        fr.save(path.with_name("copy.dcm"))
    fr.save(path.with_name("copy.npz"))                                  # what it says to do instead
    assert read_frames(path.with_name("copy.npz")).spacing == pytest.approx((0.1, 0.12))


def test_rgb_to_luma_weights_and_monochrome1(tmp_path):
    rgb = np.zeros((1, 50, 60, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 100, 110, 120              # near grey: 20 levels apart, below 25
    fr = read_frames(write_dicom(tmp_path / "a.dcm", rgb, [region(0, 0, 59, 49)]))
    assert fr.frames[0, 0, 0] == pytest.approx(0.299 * 100 + 0.587 * 110 + 0.114 * 120, abs=1e-4)
    # YBR_FULL (stored as a scanner's JPEG would decode it): the luma is its Y
    ybr = np.zeros((1, 50, 60, 3), np.uint8)
    ybr[..., 0] = np.arange(60, dtype=np.uint8)[None, None, :] * 4
    ybr[..., 1:] = 128
    fy = read_frames(write_dicom(tmp_path / "y.dcm", ybr, [region(0, 0, 59, 49)], photometric="YBR_FULL"))
    np.testing.assert_allclose(fy.frames[0], ybr[0, ..., 0], atol=1.0)   # within pydicom's RGB rounding
    g = np.arange(50 * 60).reshape(1, 50, 60) % 256
    m1 = read_frames(write_dicom(tmp_path / "m1.dcm", g, [region(0, 0, 59, 49)], photometric="MONOCHROME1"))
    np.testing.assert_array_equal(m1.frames, 255 - g)                # MONOCHROME1: 0 is white
    assert "inverted" in m1.metadata["colour"]


def test_largest_tissue_region_and_reference_pixel_origin(tmp_path):
    tissue = np.random.default_rng(2).integers(0, 256, (1, 160, 200)).astype(np.uint8)
    small = region(270, 40, 310, 80, dx_cm=0.05, dy_cm=0.05)
    # the reference pixel: column 100 of the region is lateral 0, row 0 is depth 0.5 cm (region starts below skin)
    main_r = region(ref=(100, 0, 0.0, 0.5))
    bar = region(0, 0, 10, 10, data_type=13)                            # a grey bar, not tissue
    fr = read_frames(write_dicom(tmp_path / "r.dcm", screen(tissue), [small, bar, main_r]))
    assert fr.frames.shape == (1, 160, 200) and fr.metadata["region"]["index"] == 2
    assert fr.origin == pytest.approx((5.0, -12.0), abs=1e-9)           # (0.5 cm, -100 x 0.012 cm) in mm


def test_folder_of_single_frames_sorted_by_instance_number(tmp_path):
    rng = np.random.default_rng(3)
    tissue = rng.integers(0, 256, (3, 160, 200)).astype(np.uint8)
    folder = tmp_path / "series"
    folder.mkdir()
    # names in the opposite order of the instances, and one without an extension (DICM marker only)
    write_dicom(folder / "c.dcm", screen(tissue[:1]), [region()], instance=1)
    write_dicom(folder / "b.dcm", screen(tissue[1:2]), [region()], instance=2)
    write_dicom(folder / "a", screen(tissue[2:]), [region()], instance=3)
    (folder / "notes.txt").write_text("operator notes")
    fr = read_frames(folder)
    assert fr.frames.shape == (3, 160, 200) and fr.metadata["files"] == ["c.dcm", "b.dcm", "a"]
    np.testing.assert_allclose(fr.frames, tissue, atol=1e-3)
    assert fr.spacing == pytest.approx((0.1, 0.12))
    write_dicom(folder / "d.dcm", screen(tissue[:1]), [region()], instance=4, series=generate_uid())
    with pytest.raises(FileFormatError, match="2 DICOM series"):
        read_frames(folder)


def test_extensionless_file_with_the_dicm_marker(loop, tmp_path):
    path, tissue = loop
    bare = tmp_path / "IM_0002"
    bare.write_bytes(path.read_bytes())
    uid_named = tmp_path / "1.2.840.113619.2.55"                       # a UID's digits look like an extension
    uid_named.write_bytes(path.read_bytes())
    for p in (bare, uid_named):
        assert detect_format(p) == "dicom"
        np.testing.assert_allclose(read_frames(p).frames, tissue, atol=1e-3)


def test_no_regions_needs_spacing(tmp_path, capsys):
    g = np.random.default_rng(4).integers(0, 256, (2, 80, 90)).astype(np.uint8)
    path = write_dicom(tmp_path / "plain.dcm", g)
    with pytest.raises(InputError, match="no SequenceOfUltrasoundRegions.*--spacing DX DY"):
        read_frames(path)
    fr = read_frames(path, spacing=(0.1, 0.1))
    assert fr.frames.shape == (2, 80, 90)                                # the whole image: no region to crop to
    assert main(["track", str(path), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "--spacing DX DY" in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.parametrize("units,needle", [((3, 12), "PhysicalUnitsYDirection is degrees"),
                                          ((4, 3), "PhysicalUnitsXDirection is seconds")])
def test_units_other_than_cm_are_refused(tmp_path, units, needle):
    g = np.zeros((1, 240, 320), np.uint8)
    with pytest.raises(FileFormatError, match=needle):
        read_frames(write_dicom(tmp_path / "u.dcm", g, [region(units=units)]))


def test_colour_doppler_is_refused(tmp_path, capsys):
    rng = np.random.default_rng(5)
    tissue = rng.integers(0, 256, (2, 160, 200)).astype(np.uint8)
    frames = screen(tissue)
    # red / blue flow inside the tissue region, its velocities changing from frame to frame; no flow region
    flow = rng.integers(100, 256, (2, 60, 80))
    frames[:, 80:140, 120:200, 0] = flow
    frames[:, 80:140, 120:200, 1] = 20
    frames[:, 80:140, 120:200, 2] = 255 - flow
    path = write_dicom(tmp_path / "cd.dcm", frames, [region()])
    with pytest.raises(FileFormatError, match="coloured .*differently from frame to frame.*strain from colour-coded "
                                              "pixels is meaningless"):
        read_frames(path)
    # one frame of it: nothing to tell flow from an overlay, every coloured pixel counts
    with pytest.raises(FileFormatError, match="coloured.*meaningless"):
        read_frames(write_dicom(tmp_path / "cd1.dcm", frames[:1], [region()]))
    # a colour-flow region over the tissue region
    path2 = write_dicom(tmp_path / "cd2.dcm", screen(tissue), [region(), region(100, 60, 200, 150, data_type=2)])
    assert main(["info", str(path2)]) == 2
    err = capsys.readouterr().err
    assert "colour-flow" in err and "meaningless" in err, err
    # a scanner's power-Doppler image of a lymph node (pydicom's example, no regions): 6.0 % coloured
    from pydicom.data import get_testdata_file

    with pytest.raises(FileFormatError, match=r"6\.0 % of the image's .* meaningless"):
        read_frames(get_testdata_file("examples_rgb_color.dcm"), spacing=(0.1, 0.1))
    # a small coloured marker (a caliper) in the tissue region is accepted
    frames = screen(tissue)
    frames[:, 100:104, 150:160] = (0, 255, 0)
    assert read_frames(write_dicom(tmp_path / "cal.dcm", frames, [region()])).n_frames == 2
    # a body marker / logo burned in at one place, alike in every frame (7.5 % of the region): an overlay, named
    frames = screen(tissue)
    frames[:, 60:100, 80:140] = (255, 200, 0)
    fr = read_frames(write_dicom(tmp_path / "logo.dcm", frames, [region()]))
    assert fr.metadata["overlay_fraction"] == pytest.approx(40 * 60 / (160 * 200))
    assert "overlay fixed on the screen (7.5 %" in fr.metadata["colour"] and "--roi" in fr.metadata["colour"]


def test_given_spacing_against_the_calibration(loop, tmp_path, capsys):
    path, _ = loop
    out = str(tmp_path / "t")
    # 0.2 mm axial against the header's 0.1: refused, both values named
    assert main(["track", str(path), "-o", out, "--spacing", "0.2", "0.12"]) == 2
    err = capsys.readouterr().err
    assert "axial 0.2 mm against 0.1 mm" in err and "--no-orientation-check" in err, err
    assert main(["register", str(path), "-o", out + ".npz", "--spacing", "auto", "0.2"]) == 2
    assert "lateral 0.2 mm against 0.12 mm" in capsys.readouterr().err
    # within 1 %: read, and the value given is used
    assert read_frames(path, spacing=(0.1005, 0.12)).spacing == (0.1005, 0.12)
    with pytest.raises(InputError, match="contradicts"):
        read_frames(path, spacing=(0.2, None))
    assert read_frames(path, spacing=(0.2, None), check_orientation=False).spacing == pytest.approx((0.2, 0.12))


def test_transpose_exchanges_the_calibration_before_comparing_a_given_spacing(tmp_path, capsys):
    # a loop stored lines first (rows lateral, 0.1 mm; columns axial, 0.12 mm), as a frame.T export leaves it
    tissue = np.random.default_rng(4).integers(0, 256, (3, 160, 200)).astype(np.uint8)
    path = write_dicom(tmp_path / "T.dcm", screen(tissue), [region(ref=(100, 0, 0.0, 0.5))])
    fr = read_frames(path, transpose=True)
    assert fr.frames.shape == (3, 200, 160) and fr.spacing == pytest.approx((0.12, 0.1))
    assert fr.metadata["header_spacing"] == pytest.approx([0.12, 0.1])
    assert fr.origin == pytest.approx((-12.0, 5.0), abs=1e-9)           # the reference pixel's, exchanged too
    # the transposed frames' spacing (axial, lateral) agrees with the calibration: read (refused before)
    assert read_frames(path, transpose=True, spacing=(0.12, 0.1)).spacing == (0.12, 0.1)
    with pytest.raises(InputError, match=r"axial 0.1 mm against 0.12 mm; lateral 0.12 mm against 0.1 mm"):
        read_frames(path, transpose=True, spacing=(0.1, 0.12))          # the file's order: contradicts
    assert main(["info", str(path), "--transpose", "--spacing", "0.12", "0.1"]) in (0, 1)
    out, err = capsys.readouterr()
    assert "contradicts" not in err and "0.12 mm axial, 0.1 mm lateral" in out, (out, err)
    assert main(["info", str(path), "--transpose", "--spacing", "0.1", "0.12"]) == 1   # described, needs a fix
    assert "contradicts the file's calibration" in capsys.readouterr().out
    assert main(["track", str(path), "--transpose", "--spacing", "0.1", "0.12", "-o", str(tmp_path / "t")]) == 2
    err = capsys.readouterr().err
    assert "contradicts the file's calibration" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "t").exists()


def test_compressed_with_a_decoder(loop, tmp_path):
    from pydicom.pixels import get_decoder
    from pydicom.uid import RLELossless

    if not get_decoder(RLELossless).is_available:       # pydicom's own RLE decoder: always there
        pytest.fail("pydicom cannot decode RLE Lossless")
    path, tissue = loop
    ds = pydicom.dcmread(path)
    ds.compress(RLELossless)
    ds.save_as(tmp_path / "rle.dcm", enforce_file_format=True)
    fr = read_frames(tmp_path / "rle.dcm")
    assert fr.metadata["transfer_syntax"] == "RLE Lossless"
    np.testing.assert_allclose(fr.frames, tissue, atol=1e-3)


def test_compressed_without_a_decoder(loop, tmp_path, capsys, monkeypatch):
    import pydicom.pixels
    from pydicom.uid import JPEGLSLossless

    real = pydicom.pixels.get_decoder(JPEGLSLossless)
    if real.is_available:           # a JPEG-LS plugin is installed here: the reader is told it is not
        class Missing:
            is_available = False
            missing_dependencies = ["pylibjpeg - requires pylibjpeg>=2.0 and pylibjpeg-libjpeg>=2.1"]

        monkeypatch.setattr(pydicom.pixels, "get_decoder", lambda uid: Missing())
    path, _ = loop
    ds = pydicom.dcmread(path)
    ds.file_meta.TransferSyntaxUID = JPEGLSLossless
    from pydicom.encaps import encapsulate

    ds.PixelData = encapsulate([b"\xff\xd8\xff\xf7" + bytes(60)] * int(ds.NumberOfFrames))
    ds["PixelData"].VR = "OB"
    ds.save_as(tmp_path / "jls.dcm", enforce_file_format=True)
    assert main(["info", str(tmp_path / "jls.dcm")]) == 2
    err = capsys.readouterr().err
    assert "JPEG-LS" in err and "pylibjpeg" in err and "pillow" in err and "Traceback" not in err, err


def test_without_pydicom_the_error_names_the_extra(loop, monkeypatch, capsys):
    path, _ = loop
    monkeypatch.setitem(sys.modules, "pydicom", None)                    # import pydicom -> ImportError
    with pytest.raises(FileFormatError, match=r"femreg\[dicom\]"):
        read_frames(path)
    assert main(["info", str(path)]) == 2
    assert "pip install 'femreg[dicom]'" in capsys.readouterr().err


def test_info_says_what_was_read(loop, capsys):
    path, _ = loop
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    for needle in ("dicom", "frames    4", "160 axial x 200 lateral", "0.1 mm axial, 0.12 mm lateral",
                   "DICOM ultrasound region 0 of 1", "PhysicalDeltaY 0.01 cm", "rows 40-199, columns 60-259",
                   "RGB converted to luma", "frame rate 25 Hz (FrameTime 40 ms)", "B-mode", "needs     nothing"):
        assert needle in out, (needle, out)
    assert main(["info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["spacing_mm"] == pytest.approx([0.1, 0.12]) and info["metadata"]["frame_rate"] == pytest.approx(25)


def test_bmode_loop_as_dicom_registers_to_its_known_strain(tmp_path, capsys):
    """A clinic-like loop: RF speckle (20 dB SNR) compressed 1 % axially and shifted 0.3 mm laterally, turned into
    8-bit log-compressed B-mode on 0.1 mm pixels, placed on an RGB screen with burned-in text, its region's
    reference pixel putting the first row at depth 2 mm and column 70 at lateral 0; registered by
    ``femreg register`` and ``femreg track`` from the DICOM file alone."""
    import femreg
    from scipy import ndimage

    from femreg.speckle import envelope
    from femreg.synthetic import speckle_pair

    eps, shift, origin = -0.01, 0.3, (2.0, -7.0)
    x_mid = origin[0] + 600 * 0.02 / 2

    def disp(p):
        return np.column_stack([eps * (p[:, 0] - x_mid), np.full(len(p), shift)])

    ref, mov = speckle_pair(disp, (600, 140), (0.02, 0.1), origin, seed=3, lateral_fwhm=0.8, snr_db=20)

    def bmode(rf, q=5):                     # envelope low-passed and resampled to 0.1 mm, 50 dB, 8 bits
        env = ndimage.gaussian_filter1d(envelope(rf), q / 2, axis=0)[::q]
        db = 20 * np.log10(env / env.max() + 1e-6)
        return np.clip((db + 50) / 50 * 255, 0, 255).astype(np.uint8)

    a, b = bmode(ref), bmode(mov)
    path = write_dicom(tmp_path / "loop.dcm", screen(np.stack([a, b]), rows=180, cols=220, x0=40, y0=30),
                       [region(40, 30, 179, 149, dx_cm=0.01, dy_cm=0.01, ref=(70, 0, 0.0, 0.2))], frame_time=50.0)
    fr = read_frames(path)
    assert fr.origin == pytest.approx(origin) and fr.spacing == pytest.approx((0.1, 0.1))
    assert femreg.orientation.is_envelope(fr.frames[0])               # B-mode: no RF carrier

    assert main(["register", str(path), "-o", str(tmp_path / "pair.npz")]) == 0
    out = capsys.readouterr().out
    assert "envelope / B-mode data" in out                               # registered as B-mode, and said so
    assert main(["track", str(path), "-o", str(tmp_path / "trk"), "--no-progress"]) == 0
    for res in (femreg.load_result(tmp_path / "pair.npz"), femreg.load_result(tmp_path / "trk" / "frame_001.npz")):
        pts = res.pixel_points()
        u, e = res.displacement(pts), res.strain(pts)
        ok = np.isfinite(u).all(1) & np.isfinite(e).all(1)
        rms = float(np.sqrt(np.mean(np.sum((u[ok] - disp(pts[ok])) ** 2, axis=1))))
        # measured 0.79 um RMS (0.008 pixel) and axial strain -0.00997: bounds 6x and 5 % of the strain
        assert rms < 5e-3, rms
        assert abs(np.median(e[ok, 0]) - eps) < 0.05 * abs(eps), np.median(e[ok, 0])


def test_a_scanners_export(tmp_path):
    """pydicom's SonoSite cardiac loop (30 frames, YBR_FULL_422, JPEG baseline, decoded by Pillow): stored at half
    the size its regions were written for, it is refused; with its region halved (and the deltas doubled) it is read,
    cropped to the fan, its luma the Y the scanner stored, its green marker under the colour threshold."""
    from pydicom.data import get_testdata_file
    from pydicom.pixels import get_decoder, pixel_array

    import femreg

    src = get_testdata_file("examples_ybr_color.dcm")
    assert src is not None, "pydicom's example files are part of its wheel"
    ds = pydicom.dcmread(src)
    if not get_decoder(ds.file_meta.TransferSyntaxUID).is_available:
        pytest.fail("Pillow (a matplotlib dependency) decodes JPEG baseline")
    with pytest.raises(FileFormatError, match="resized or cropped"):
        read_frames(src)
    r = ds.SequenceOfUltrasoundRegions[0]
    for k in ("RegionLocationMinX0", "RegionLocationMinY0", "RegionLocationMaxX1", "RegionLocationMaxY1"):
        setattr(r, k, int(getattr(r, k)) // 2)
    r.PhysicalDeltaX, r.PhysicalDeltaY = 2 * r.PhysicalDeltaX, 2 * r.PhysicalDeltaY
    ds.save_as(tmp_path / "sonosite.dcm")
    fr = read_frames(tmp_path / "sonosite.dcm")
    assert fr.frames.shape == (30, 193, 256)
    assert fr.spacing == pytest.approx((1.02099, 1.02099), rel=1e-5)
    assert fr.metadata["frame_rate"] == pytest.approx(30.0, rel=1e-4)
    y = pixel_array(ds, index=0, as_rgb=False)[15:208, 42:298, 0].astype(np.float32)
    # measured: mean 0.013 grey levels from the stored Y, 6.5 at most (the green marker, clipped in RGB)
    assert np.mean(np.abs(fr.frames[0] - y)) < 0.1 and np.max(np.abs(fr.frames[0] - y)) < 10
    assert femreg.orientation.is_envelope(fr.frames[0])
