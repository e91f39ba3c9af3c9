"""Strict image decoding: whole JPEGs and PNGs decode, cut ones are refused."""

import cv2
import numpy as np
import pytest

from converters.image_codec import ImageDecodeError, decode, read


@pytest.fixture
def image():
    return np.random.default_rng(0).integers(0, 255, (48, 64, 3), np.uint8)


@pytest.mark.parametrize("extension", [".jpg", ".png"])
def test_a_whole_image_decodes_also_with_trailing_padding(image, extension):
    data = cv2.imencode(extension, image)[1].tobytes()
    for padded in (data, data + b"\x00\x00\r\n"):
        decoded = decode(padded, cv2.IMREAD_COLOR)
        assert decoded.shape == image.shape
        if extension == ".png":
            assert np.array_equal(decoded, image)


@pytest.mark.parametrize(("extension", "message"), [(".jpg", "truncated JPEG"),
                                                    (".png", "truncated PNG")])  # fmt: skip
@pytest.mark.parametrize("keep", [0.5, 0.9, 0.999])
def test_a_cut_image_is_refused(image, extension, message, keep):
    data = cv2.imencode(extension, image)[1].tobytes()
    with pytest.raises(ImageDecodeError, match=message):
        decode(data[: int(len(data) * keep)], cv2.IMREAD_COLOR, "colour image")


def test_garbage_and_unreadable_files_name_the_file(tmp_path):
    with pytest.raises(ImageDecodeError, match="corrupt or truncated"):
        decode(b"not an image at all", cv2.IMREAD_COLOR)
    missing = tmp_path / "missing.png"
    with pytest.raises(ImageDecodeError, match=f"{missing}: cannot be read"):
        read(missing, cv2.IMREAD_UNCHANGED)
