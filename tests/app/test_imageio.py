"""app.files.imageio: every supported input format reads back the exact samples written."""

import cv2
import h5py
import numpy as np
import pytest
import tifffile

from app.files import imageio
from app.files.imageio import ImageReadError
from tests.datapaths import NEEDLE, TRAPPED


@pytest.fixture
def image8(rng):
    return rng.integers(0, 256, size=(37, 53), dtype=np.uint8)


@pytest.fixture
def image16(rng):
    return rng.integers(0, 4096, size=(37, 53), dtype=np.uint16)


@pytest.mark.parametrize("suffix", [".png", ".bmp", ".tif"])
def test_8bit_round_trip_is_exact(tmp_path, image8, suffix):
    path = imageio.write_image(tmp_path / f"a{suffix}", image8)
    back = imageio.read_image(path)
    assert back.dtype == np.uint8
    np.testing.assert_array_equal(back, image8)
    info = imageio.image_info(path)
    assert (info.n_frames, info.shape, info.bits) == (1, image8.shape, 8)


@pytest.mark.parametrize("suffix", [".png", ".tif"])
def test_16bit_round_trip_is_exact_and_unscaled(tmp_path, image16, suffix):
    path = imageio.write_image(tmp_path / f"a{suffix}", image16)
    back = imageio.read_image(path)
    assert back.dtype == np.uint16
    np.testing.assert_array_equal(back, image16)  # 12-bit values stay 0..4095


def test_float_tiff_reads_as_float32(tmp_path, rng):
    image = rng.normal(100.0, 5.0, size=(20, 30))
    tifffile.imwrite(tmp_path / "f.tif", image)
    back = imageio.read_image(tmp_path / "f.tif")
    assert back.dtype == np.float32
    np.testing.assert_allclose(back, image, rtol=1e-6)


def test_colour_bmp_becomes_grey_with_luma_weights(tmp_path, image8):
    bgr = np.dstack([image8, image8 // 2, image8 // 3])
    cv2.imwrite(str(tmp_path / "c.bmp"), bgr)
    back = imageio.read_image(tmp_path / "c.bmp")
    expected = 0.114 * bgr[..., 0] + 0.587 * bgr[..., 1] + 0.299 * bgr[..., 2]
    assert back.shape == image8.shape
    assert np.max(np.abs(back - expected)) <= 1.0  # rounding only


def test_grey_stored_as_rgb_is_taken_exactly(tmp_path, image8):
    cv2.imwrite(str(tmp_path / "g.png"), np.dstack([image8] * 3))
    np.testing.assert_array_equal(imageio.read_image(tmp_path / "g.png"), image8)


def test_packed_10bit_camera_tiff_keeps_its_10_bit_scale():
    path = TRAPPED / "reference_df.tif"
    with tifffile.TiffFile(path) as tif:
        assert tif.pages[0].bitspersample == 10  # the file really is packed 10-bit
    image = imageio.read_image(path)
    info = imageio.image_info(path)
    assert image.dtype == np.uint16 and image.shape == (1024, 1024)
    assert info.bits == 10
    assert image.max() <= 1023  # not stretched to 16 bit
    assert image.max() >= 1000  # but the full 10-bit range is used: unpacked, not truncated
    # the checkerboard is there: strong contrast, not noise
    assert np.percentile(image, 95) - np.percentile(image, 5) > 300


def test_real_8bit_needle_images_read():
    ref = imageio.read_image(NEEDLE / "reference_2.png")
    frame = imageio.read_image(NEEDLE / "202406_1457001661.bmp")
    assert ref.shape == frame.shape == (1024, 1024)
    assert ref.dtype == frame.dtype == np.uint8


def test_tiff_stack_iterates_page_by_page_with_selection(tmp_path, rng):
    stack = rng.integers(0, 1024, size=(7, 16, 24), dtype=np.uint16)
    tifffile.imwrite(tmp_path / "s.tif", stack, photometric="minisblack")
    single = rng.integers(0, 256, size=(16, 24), dtype=np.uint8)
    imageio.write_image(tmp_path / "t.png", single)
    paths = [tmp_path / "s.tif", tmp_path / "t.png"]
    assert imageio.count_frames(paths) == 8
    items = list(imageio.iter_frames(paths, first=1, last=7, step=3))
    assert [i.sequence_index for i in items] == [1, 4, 7]
    np.testing.assert_array_equal(items[0].image, stack[1])
    np.testing.assert_array_equal(items[1].image, stack[4])
    np.testing.assert_array_equal(items[2].image, single)
    assert items[0].label.endswith("s.tif[1]") and items[2].index_in_source == 0


@pytest.mark.parametrize("n", [3, 4])
def test_a_stack_of_3_or_4_frames_that_tifffile_stored_as_colour_planes_is_read_as_its_frames(tmp_path, rng, n,
                                                                                             caplog):
    """``tifffile.imwrite(np.stack(frames))`` of 3 or 4 grey frames stores one RGB(A) page of separate planes
    (tifffile warns that its next versions will store grey pages): read as one colour image, converted to
    grey, two or three frames were lost with exit 0 (by-hand trial of 7 Dec 2026). Now its frames, said
    once; a colour image with its planes last, and separate planes without tifffile's shape, stay one frame."""
    import warnings

    frames = rng.integers(0, 4096, (n, 24, 32)).astype(np.uint16)
    p = tmp_path / "stack.tif"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        tifffile.imwrite(p, frames)
    with tifffile.TiffFile(p) as tif:
        assert len(tif.pages) == 1  # (the layout this is about)
    with caplog.at_level("WARNING", logger="app.files.imageio"):
        got = [item.image for item in imageio.iter_frames([p])]
        assert imageio.count_frames([p]) == n
    np.testing.assert_array_equal(np.stack(got), frames)
    said = [r.getMessage() for r in caplog.records if "separate planes" in r.getMessage()]
    assert len(said) == 1 and f"read as {n} grey frames" in said[0], said
    colour = rng.integers(0, 256, (24, 32, 3)).astype(np.uint8)
    tifffile.imwrite(tmp_path / "colour.tif", colour)
    tifffile.imwrite(tmp_path / "planar.tif", np.moveaxis(colour, -1, 0), photometric="rgb",
                     planarconfig="separate", metadata=None)
    for name in ("colour.tif", "planar.tif"):
        assert imageio.count_frames([tmp_path / name]) == 1
        assert imageio.read_image(tmp_path / name).shape == (24, 32)


@pytest.mark.parametrize("compression", [None, "zlib"])
def test_such_a_stack_cut_short_keeps_the_frames_before_the_cut(tmp_path, rng, compression):
    """The same 4-frame stack cut in its third plane (an interrupted copy): tifffile reads the page's planes
    together, and its short read ended `process` with a ValueError traceback, every frame lost (by-hand
    trial of 7 Dec 2026). Now each plane is read alone: the two whole ones as written, the cut ones
    unreadable frames that say the file is truncated. Compressed planes cannot be read alone: each frame
    then says it cannot be read, none raises."""
    import warnings

    frames = rng.integers(0, 4096, (4, 24, 32)).astype(np.uint16)
    whole, cut = tmp_path / "stack.tif", tmp_path / "cut.tif"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        tifffile.imwrite(whole, frames, compression=compression)
    data = whole.read_bytes()
    with tifffile.TiffFile(whole) as tif:
        page = tif.pages[0]
        end = int(page.dataoffsets[-1]) + int(page.databytecounts[-1])
        plane_start = int(page.dataoffsets[2 * len(page.dataoffsets) // 4])
    cut.write_bytes(data[:plane_start + (end - plane_start) // 4])  # in the third plane
    items = list(imageio.iter_frames([cut], errors="yield"))
    assert len(items) == 4
    if compression is None:
        for k in (0, 1):
            np.testing.assert_array_equal(items[k].image, frames[k])
        for k in (2, 3):
            assert items[k].image is None and "is missing: the file is truncated" in str(items[k].error)
            assert f"frame {k} (plane {k} of its one page) is cut off" in str(items[k].error)
    else:
        assert all(item.image is None and "may be truncated" in str(item.error) for item in items)


def test_stack_needs_an_index_to_be_read_as_one_image(tmp_path, rng):
    stack = rng.integers(0, 255, size=(3, 8, 8), dtype=np.uint8)
    tifffile.imwrite(tmp_path / "s.tif", stack, photometric="minisblack")
    with pytest.raises(ImageReadError, match="holds 3 pages"):
        imageio.read_image(tmp_path / "s.tif")
    np.testing.assert_array_equal(imageio.read_image(tmp_path / "s.tif", index=2), stack[2])


def test_recording_frames_and_reference(tmp_path, rng):
    frames = rng.integers(0, 4096, size=(5, 12, 18), dtype=np.uint16)
    reference = rng.integers(0, 4096, size=(12, 18), dtype=np.uint16)
    path = tmp_path / "rec.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("frames", data=frames, chunks=(1, 12, 18))
        f.create_dataset("reference", data=reference)
        f["frames"].attrs["bits"] = 12
    info = imageio.image_info(path)
    assert (info.kind, info.n_frames, info.shape, info.bits) == ("recording", 5, (12, 18), 12)
    np.testing.assert_array_equal(imageio.read_reference(path), reference)
    items = list(imageio.iter_frames([path], first=2))
    assert [i.index_in_source for i in items] == [2, 3, 4]
    np.testing.assert_array_equal(items[0].image, frames[2])


def test_recording_without_reference_uses_first_frame(tmp_path, rng, caplog):
    frames = rng.integers(0, 255, size=(2, 6, 6), dtype=np.uint8)
    with h5py.File(tmp_path / "rec.h5", "w") as f:
        f.create_dataset("frames", data=frames)
    np.testing.assert_array_equal(imageio.read_reference(tmp_path / "rec.h5"), frames[0])
    assert "first frame" in caplog.text


def test_recording_stopped_early_reads_only_written_frames(tmp_path, rng):
    frames = rng.integers(0, 255, size=(6, 4, 4), dtype=np.uint8)
    with h5py.File(tmp_path / "rec.h5", "w") as f:
        f.create_dataset("frames", data=frames)
        f.attrs["frames_written"] = 4
    assert imageio.frame_count(tmp_path / "rec.h5") == 4


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda d: d / "missing.png", "does not exist"),
        (lambda d: d, "is a directory"),
        (lambda d: (d / "x.png").write_text("not an image") and d / "x.png", "not a readable image"),
        (lambda d: (d / "x.tif").write_text("not a tiff") and d / "x.tif", "not a readable TIFF"),
        (lambda d: (d / "x.h5").write_text("not hdf5") and d / "x.h5", "not a readable HDF5"),
        (lambda d: (d / "e.png").write_bytes(b"") or d / "e.png", "empty"),
    ],
)
def test_bad_files_raise_messages_naming_the_file(tmp_path, make, match):
    path = make(tmp_path)
    with pytest.raises(ImageReadError, match=match) as err:
        imageio.read_image(path)
    assert str(path) in str(err.value)


def test_hdf5_without_frames_says_what_it_is(tmp_path):
    with h5py.File(tmp_path / "out.h5", "w") as f:
        f.create_dataset("height", data=np.zeros((1, 2, 2)))
    with pytest.raises(ImageReadError, match="process` output, not a recording"):
        imageio.image_info(tmp_path / "out.h5")
