"""Image I/O: exact EXR round trips, contiguity, atomic writes, PNG through the display transform."""
import os

import numpy as np
import pytest

from suite.core import imageio
from suite.errors import UserError
from suite.core.imageio import read_exr, write_exr, write_png


def random_image(seed, shape=(12, 20, 3)):
    return (np.random.default_rng(seed).random(shape) * 4.0).astype(np.float32)


@pytest.mark.parametrize("shape", [(12, 20, 3), (12, 20), (12, 20, 4), (5, 7, 6)])
def test01_exr_round_trip_is_bit_exact(tmp_path, shape):
    img = random_image(1, shape)
    write_exr(tmp_path / "img.exr", img)
    back = read_exr(tmp_path / "img.exr")
    assert back.dtype == np.float32 and back.flags.c_contiguous
    np.testing.assert_array_equal(back, img)


def test02_one_channel_image_reads_back_as_two_dimensional(tmp_path):
    write_exr(tmp_path / "gray.exr", random_image(2, (6, 5, 1)))
    assert read_exr(tmp_path / "gray.exr").shape == (6, 5)


@pytest.mark.parametrize("view", ["transposed", "reversed", "strided"])
def test03_non_contiguous_input_is_written_correctly(tmp_path, view):
    base = random_image(3, (20, 12, 3))
    img = {"transposed": base.transpose(1, 0, 2), "reversed": base[::-1, ::-1], "strided": base[::2, ::3]}[view]
    assert not img.flags.c_contiguous
    write_exr(tmp_path / "view.exr", img)
    np.testing.assert_array_equal(read_exr(tmp_path / "view.exr"), np.ascontiguousarray(img))


def test04_float64_input_is_stored_as_float32(tmp_path):
    img = random_image(4).astype(np.float64) + 1e-9
    write_exr(tmp_path / "f64.exr", img)
    np.testing.assert_array_equal(read_exr(tmp_path / "f64.exr"), img.astype(np.float32))


def test05_missing_file_is_a_user_error_naming_it(tmp_path):
    missing = tmp_path / "nothere.exr"
    with pytest.raises(UserError, match="nothere.exr"):
        read_exr(missing)


def test06_truncated_file_is_a_user_error_naming_it(tmp_path):
    path = tmp_path / "cut.exr"
    write_exr(path, random_image(5, (64, 64, 3)))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(UserError, match="cut.exr"):
        read_exr(path)


def test07_garbage_file_is_a_user_error_naming_it(tmp_path):
    path = tmp_path / "noise.exr"
    path.write_bytes(b"not an image at all")
    with pytest.raises(UserError, match="noise.exr"):
        read_exr(path)


class _FailingOutput:
    """An ImageOutput that opens (creating the file) and then fails to write, as OpenImageIO does on
    a bad buffer: write_image returns False and the file is left half-written."""

    def __init__(self, real):
        self.real = real

    def open(self, name, spec):
        self.name = name
        return self.real.open(name, spec)

    def write_image(self, pixels):
        return False

    def geterror(self):
        return "simulated write failure"

    def close(self):
        return self.real.close()


@pytest.mark.parametrize("writer", ["exr", "png"])
def test08_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path, monkeypatch, writer):
    import OpenImageIO as oiio

    path = tmp_path / f"keep.{writer}"
    write = {"exr": write_exr, "png": write_png}[writer]
    write(path, random_image(6) / 4.0)
    before = path.read_bytes()

    class FailingModule:
        FLOAT, UINT8, ImageSpec, geterror = oiio.FLOAT, oiio.UINT8, oiio.ImageSpec, staticmethod(oiio.geterror)

        class ImageOutput:
            @staticmethod
            def create(name):
                return _FailingOutput(oiio.ImageOutput.create(name))

    monkeypatch.setattr(imageio, "_oiio", lambda: FailingModule)
    with pytest.raises(UserError, match="simulated write failure"):
        write(path, random_image(7) / 4.0)
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == [path.name]


def test09_interrupted_write_leaves_no_file(tmp_path, monkeypatch):
    import OpenImageIO as oiio

    class Interrupted(Exception):
        pass

    class InterruptingOutput(_FailingOutput):
        def write_image(self, pixels):
            raise Interrupted()

    class InterruptingModule:
        FLOAT, UINT8, ImageSpec, geterror = oiio.FLOAT, oiio.UINT8, oiio.ImageSpec, staticmethod(oiio.geterror)

        class ImageOutput:
            @staticmethod
            def create(name):
                return InterruptingOutput(oiio.ImageOutput.create(name))

    monkeypatch.setattr(imageio, "_oiio", lambda: InterruptingModule)
    with pytest.raises(Interrupted):
        write_exr(tmp_path / "new.exr", random_image(8))
    assert os.listdir(tmp_path) == []


def test10_missing_directory_is_a_user_error(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        write_exr(tmp_path / "no" / "such" / "dir.exr", random_image(9))


@pytest.mark.parametrize("bad", [np.zeros((2, 3, 4, 5)), np.zeros(7), np.zeros((0, 4, 3)), np.array([["a"]])])
def test11_bad_arrays_are_user_errors(tmp_path, bad):
    with pytest.raises(UserError):
        write_exr(tmp_path / "bad.exr", bad)
    assert os.listdir(tmp_path) == []


def test12_png_stores_the_display_transform_in_8_bits(tmp_path):
    import colour

    codes = np.arange(256, dtype=np.float64).reshape(16, 16)
    linear = colour.cctf_decoding(codes / 255.0, function="sRGB")
    rgb = np.stack([linear, linear[::-1], linear.T], axis=2)
    write_png(tmp_path / "codes.png", rgb)
    stored = np.rint(read_exr(tmp_path / "codes.png") * 255.0)
    np.testing.assert_array_equal(stored, np.stack([codes, codes[::-1], codes.T], axis=2))


def test13_png_exposure_is_a_linear_multiplier(tmp_path):
    img = random_image(10) / 8.0
    write_png(tmp_path / "exposed.png", img, exposure=3.0)
    write_png(tmp_path / "scaled.png", 3.0 * img)
    assert (tmp_path / "exposed.png").read_bytes() == (tmp_path / "scaled.png").read_bytes()


def test14_png_with_nan_is_a_user_error(tmp_path):
    img = random_image(11)
    img[0, 0, 0] = np.nan
    with pytest.raises(UserError, match="1 NaN/Inf"):
        write_png(tmp_path / "nan.png", img)
    assert os.listdir(tmp_path) == []


def test15_written_files_get_the_umask_mode_not_mkstemps_private_mode(tmp_path):
    umask = os.umask(0o022)
    os.umask(umask)
    write_exr(tmp_path / "a.exr", random_image(12))
    write_png(tmp_path / "a.png", random_image(12))
    for name in ("a.exr", "a.png"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o666 & ~umask, name
