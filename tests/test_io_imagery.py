"""RGB image stacks: hue, masks, coordinates, dates, round trips and errors (io/imagery.py)."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import tifffile
import xarray as xr
from PIL import Image
from scipy.ndimage import binary_dilation, distance_transform_edt
from skimage.color import rgb2hsv
from skimage.feature import canny
from skimage.morphology import disk

from lrm_cvx.errors import DataError, RegionError
from lrm_cvx.io import imagery
from lrm_cvx.io.imagery import field_bbox, hue_to_value, open_image_stack, write_image_stack
from lrm_cvx.io.samples import synthetic_field

BBOX = (40.0, -80.0, 48.0, -68.0)  # south, west, north, east
NY, NX = 40, 60
# thresholds no ratio p/q with q <= 255 can equal, so the float rule has no ties
EXACT = dict(saturation_min=0.2037, value_max=0.6021, dark_max=0.0513)


def _save(path: Path, arr: np.ndarray) -> Path:
    Image.fromarray(arr).save(path)
    return path


def _random_rgb(rng: np.random.Generator, shape=(NY, NX)) -> np.ndarray:
    return rng.integers(0, 256, size=shape + (3,), dtype=np.uint8)


def _reference_hue(img: np.ndarray) -> np.ndarray:
    hue = (rgb2hsv(img)[..., 0] * 360.0).astype(np.float32)
    hue[hue >= 360] = 0
    return hue


def _rule_mask(img: np.ndarray, saturation_min, value_max, dark_max) -> np.ndarray:
    """The documented cloud / no-data rule from integer channel maxima and minima."""
    mx = img.max(axis=-1).astype(np.float64)
    mn = img.min(axis=-1).astype(np.float64)
    v = mx / 255.0
    s = np.where(mx > 0, (mx - mn) / np.maximum(mx, 1), 0.0)
    return ((s < saturation_min) & (v > value_max)) | (v < dark_max)


# --------------------------------------------------------------------------- hue and masks
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_hue_matches_rgb2hsv_and_mask_matches_rule(tmp_path, seed):
    rng = np.random.default_rng(seed)
    imgs = [_random_rgb(rng) for _ in range(3)]
    # sprinkle greys, whites and blacks so every rule fires
    for img in imgs:
        grey = rng.random((NY, NX)) < 0.2
        img[grey] = rng.integers(0, 256, size=(int(grey.sum()), 1), dtype=np.uint8)
    for i, img in enumerate(imgs):
        _save(tmp_path / f"snapshot-2014-09-0{i + 1}T00_00_00Z.png", img)
    da = open_image_stack(tmp_path, BBOX, edge_sigma=None, **EXACT)
    assert da.dims == ("time", "lat", "lon") and da.shape == (3, NY, NX)
    assert da.dtype == np.float32
    for t, img in enumerate(imgs):
        expected_mask = _rule_mask(img, **EXACT)
        got = da.values[t]
        np.testing.assert_array_equal(np.isnan(got), expected_mask)
        assert 0 < expected_mask.sum() < expected_mask.size
        ref = _reference_hue(img)
        np.testing.assert_allclose(got[~expected_mask], ref[~expected_mask], atol=1e-4)
    finite = da.values[np.isfinite(da.values)]
    assert finite.min() >= 0 and finite.max() < 360


def test_cloud_black_and_grey_pixels(tmp_path):
    img = np.empty((NY, NX, 3), dtype=np.uint8)
    img[:] = (40, 160, 60)  # saturated green
    img[2:8, 2:10] = (250, 250, 250)  # white cloud
    img[2:8, 20:30] = (200, 198, 205)  # bright grey cloud
    img[12:18, 2:10] = (0, 0, 0)  # no-data fill
    img[12:18, 20:30] = (6, 8, 5)  # JPEG-ish black
    img[25:30, 2:10] = (90, 90, 90)  # dark grey: neither cloud nor no data
    img[25:30, 20:30] = (240, 230, 80)  # bright but saturated (yellow): not a cloud
    _save(tmp_path / "snapshot-2015-10-01T00_00_00Z.png", img)
    da = open_image_stack(tmp_path, BBOX, edge_sigma=None)
    mask = np.isnan(da.values[0])
    expected = np.zeros((NY, NX), dtype=bool)
    expected[2:8, 2:10] = expected[2:8, 20:30] = True
    expected[12:18, 2:10] = expected[12:18, 20:30] = True
    np.testing.assert_array_equal(mask, expected)
    np.testing.assert_array_equal(
        mask,
        _rule_mask(img, imagery.DEFAULT_SATURATION_MIN, imagery.DEFAULT_VALUE_MAX,
                   imagery.DEFAULT_DARK_MAX),
    )
    assert da.values[0, 0, 0] == pytest.approx(_reference_hue(img)[0, 0], abs=1e-4)


def test_alpha_zero_is_no_data(tmp_path):
    rng = np.random.default_rng(3)
    rgba = np.dstack([_random_rgb(rng), np.full((NY, NX), 255, np.uint8)])
    rgba[..., :3] = np.maximum(rgba[..., :3], 30)  # stay above dark_max
    rgba[..., 0] = 250  # ... and saturated enough or dark enough not to be clouds
    rgba[..., 1] = np.minimum(rgba[..., 1], 150)
    rgba[5:9, 5:15, 3] = 0
    rgba[20:25, 5:15, 3] = 128  # half transparent is data
    _save(tmp_path / "a_2014-01-01.png", rgba)
    da = open_image_stack(tmp_path, BBOX, edge_sigma=None)
    expected = np.zeros((NY, NX), bool)
    expected[5:9, 5:15] = True
    np.testing.assert_array_equal(np.isnan(da.values[0]), expected)
    ref = _reference_hue(rgba[..., :3])
    np.testing.assert_allclose(da.values[0][~expected], ref[~expected], atol=1e-4)


def _edge_image() -> np.ndarray:
    img = np.empty((NY, NX, 3), dtype=np.uint8)
    img[:] = (30, 90, 40)  # dark green (v ~ 0.35)
    img[:, 40:] = (200, 120, 20)  # step to bright orange (v ~ 0.78), both saturated
    img[20, 3:30] = (255, 40, 40)  # thin bright red line
    return img


@pytest.mark.parametrize("sigma, dilate", [(1.0, 0), (2.0, 2), (1.5, 3)])
def test_edges_are_masked_as_documented(tmp_path, sigma, dilate):
    img = _edge_image()
    _save(tmp_path / "s_2014-01-01.png", img)
    da = open_image_stack(tmp_path, BBOX, edge_sigma=sigma, edge_dilate=dilate)
    mask = np.isnan(da.values[0])
    # independent wiring: rule mask (empty here) | dilate(canny(v))
    assert not _rule_mask(img, 0.2, 0.6, 0.05).any()
    v = rgb2hsv(img)[..., 2]
    edges = canny(v, sigma=sigma, low_threshold=0.1, high_threshold=0.2)
    if dilate:
        edges = binary_dilation(edges, structure=disk(dilate))
    np.testing.assert_array_equal(mask, edges)
    # the line and the step are masked, flat areas far from them are not
    assert mask[19:22, 8:25].any(axis=0).all()  # Canny marks both sides of a thin line
    if dilate:
        assert mask[20, 8:25].all()
    assert mask[10:30, 39:41].any(axis=1).all()
    feature = np.zeros((NY, NX), bool)
    feature[20, 3:30] = True
    feature[:, 39:41] = True
    far = distance_transform_edt(~feature) > dilate + 3 * sigma + 2
    border = np.zeros((NY, NX), bool)
    border[1:-1, 1:-1] = True
    assert not mask[far & border].any()
    ref = _reference_hue(img)
    np.testing.assert_allclose(da.values[0][~mask], ref[~mask], atol=1e-4)


def test_edge_thresholds_and_disabling(tmp_path):
    img = _edge_image()
    _save(tmp_path / "s_2014-01-01.png", img)
    off = open_image_stack(tmp_path, BBOX, edge_sigma=None)
    assert not np.isnan(off.values).any()
    insensitive = open_image_stack(tmp_path, BBOX, edge_low=5.0, edge_high=6.0)
    assert not np.isnan(insensitive.values).any()
    on = open_image_stack(tmp_path, BBOX)
    assert np.isnan(on.values).any()
    assert on.attrs["edge_masking"] == "canny" and off.attrs["edge_masking"] == "none"
    assert on.attrs["edge_sigma"] == imagery.DEFAULT_EDGE_SIGMA
    assert on.attrs["edge_dilate"] == imagery.DEFAULT_EDGE_DILATE


def test_palette_and_16bit_tiff_images(tmp_path):
    rng = np.random.default_rng(5)
    img = _random_rgb(rng)
    Image.fromarray(img).quantize(64).save(tmp_path / "p_2014-01-01.png")
    pal = np.asarray(Image.open(tmp_path / "p_2014-01-01.png").convert("RGB"))
    img16 = rng.integers(0, 65536, size=(NY, NX, 3), dtype=np.uint16)
    tifffile.imwrite(tmp_path / "g_2014-01-02.tif", img16, photometric="rgb")
    da = open_image_stack(tmp_path, BBOX, edge_sigma=None, **EXACT)
    for t, ref_img in enumerate((pal, img16)):
        hsv = rgb2hsv(ref_img)
        ok = ~(((hsv[..., 1] < EXACT["saturation_min"]) & (hsv[..., 2] > EXACT["value_max"]))
               | (hsv[..., 2] < EXACT["dark_max"]))
        np.testing.assert_array_equal(np.isfinite(da.values[t]), ok)
        np.testing.assert_allclose(da.values[t][ok], _reference_hue(ref_img)[ok], atol=1e-4)


# --------------------------------------------------------------------------- coords, dates
def test_coordinates_from_bbox_and_attrs(tmp_path):
    rng = np.random.default_rng(0)
    _save(tmp_path / "snapshot-2013-09-01T00_00_00Z.jpg", _random_rgb(rng))
    da = open_image_stack(tmp_path, BBOX)
    south, west, north, east = BBOX
    dlat, dlon = (north - south) / NY, (east - west) / NX
    np.testing.assert_allclose(da["lat"].values, north - dlat * (np.arange(NY) + 0.5))
    np.testing.assert_allclose(da["lon"].values, west + dlon * (np.arange(NX) + 0.5))
    assert da["lat"].values[0] == pytest.approx(north - 0.1)
    assert da["lon"].values[-1] == pytest.approx(east - 0.1)
    assert da["lat"].attrs["units"] == "degrees_north"
    assert da["lon"].attrs["standard_name"] == "longitude"
    assert da.attrs["units"] == "degree" and da.attrs["long_name"] == "hue"
    assert "snapshot-2013-09-01T00_00_00Z.jpg" in da.attrs["source_files"]
    for key in ("saturation_min", "value_max", "dark_max"):
        assert da.attrs[key] == getattr(imagery, f"DEFAULT_{key.upper()}")


def test_dates_from_worldview_names_sorted(tmp_path):
    rng = np.random.default_rng(0)
    names = ["snapshot-2015-10-03T00_00_00Z.png", "snapshot-2013-09-01T00_00_00Z.jpg",
             "foliage_2014-11-30_extra.png", "snapshot-2014-09-15T12_30_00Z.png"]
    imgs = {n: _random_rgb(rng) for n in names}
    for n, img in imgs.items():
        Image.fromarray(img).save(tmp_path / n, quality=100, subsampling=0)
    da = open_image_stack(tmp_path, BBOX, edge_sigma=None)
    expected = [pd.Timestamp(t) for t in
                ("2013-09-01", "2014-09-15T12:30:00", "2014-11-30", "2015-10-03")]
    assert [pd.Timestamp(t) for t in da["time"].values] == expected
    files = da.attrs["source_files"].split("\n")
    assert [Path(f).name for f in files] == [names[1], names[3], names[2], names[0]]
    # the image content follows its date
    first_png = _reference_hue(imgs[names[3]])
    ok = np.isfinite(da.values[1])
    np.testing.assert_allclose(da.values[1][ok], first_png[ok], atol=1e-4)


def test_times_argument_overrides_names_and_sorts(tmp_path):
    rng = np.random.default_rng(1)
    imgs = [_random_rgb(rng) for _ in range(3)]
    paths = [_save(tmp_path / f"img{i}.png", img) for i, img in enumerate(imgs)]
    times = ["2014-09-20", "2014-09-10", "2014-09-30"]
    da = open_image_stack(paths, BBOX, times=times, edge_sigma=None, **EXACT)
    np.testing.assert_array_equal(da["time"].values, pd.to_datetime(sorted(times)).values)
    for t, i in enumerate([1, 0, 2]):
        ok = ~_rule_mask(imgs[i], **EXACT)
        np.testing.assert_allclose(da.values[t][ok], _reference_hue(imgs[i])[ok], atol=1e-4)
    with pytest.raises(DataError, match="2 dates but there are 3 images"):
        open_image_stack(paths, BBOX, times=times[:2])


def test_glob_and_single_file(tmp_path):
    rng = np.random.default_rng(2)
    _save(tmp_path / "snapshot-2013-09-01T00_00_00Z.png", _random_rgb(rng))
    _save(tmp_path / "snapshot-2013-09-02T00_00_00Z.png", _random_rgb(rng))
    (tmp_path / "notes.txt").write_text("not an image")
    assert open_image_stack(str(tmp_path / "*.png"), BBOX).sizes["time"] == 2
    one = open_image_stack(tmp_path / "snapshot-2013-09-02T00_00_00Z.png", BBOX)
    assert one.sizes["time"] == 1 and str(one["time"].values[0]).startswith("2013-09-02")


# --------------------------------------------------------------------------- errors
def test_unparseable_and_invalid_dates(tmp_path):
    rng = np.random.default_rng(0)
    _save(tmp_path / "snapshot-2013-09-01T00_00_00Z.png", _random_rgb(rng))
    _save(tmp_path / "holiday.png", _random_rgb(rng))
    with pytest.raises(DataError, match="holiday.png"):
        open_image_stack(tmp_path, BBOX)
    bad = tmp_path / "bad"
    bad.mkdir()
    _save(bad / "snapshot-2013-02-30T00_00_00Z.png", _random_rgb(rng))
    with pytest.raises(DataError, match="2013-02-30"):
        open_image_stack(bad, BBOX)


def test_dates_outside_datetime64_ns_are_refused_not_wrapped(tmp_path):
    rng = np.random.default_rng(0)
    _save(tmp_path / "snapshot-2800-03-01T00_00_00Z.png", _random_rgb(rng))
    with pytest.raises(DataError, match=r"'2800-03-01T00_00_00' in the file name .* is outside"
                                        r" .* 1677-09-21 to 2262-04-11"):
        open_image_stack(tmp_path, BBOX)
    with pytest.raises(DataError, match=r"times\[0\] = 1600-01-01 00:00:00 is outside"):
        open_image_stack(tmp_path, BBOX, times=["1600-01-01"])


def test_duplicate_dates(tmp_path):
    rng = np.random.default_rng(0)
    _save(tmp_path / "snapshot-2013-09-01T00_00_00Z.png", _random_rgb(rng))
    Image.fromarray(_random_rgb(rng)).save(tmp_path / "snapshot-2013-09-01T00_00_00Z.jpg")
    with pytest.raises(DataError, match="same time"):
        open_image_stack(tmp_path, BBOX)


def test_different_sizes_name_both_files(tmp_path):
    rng = np.random.default_rng(0)
    _save(tmp_path / "snapshot-2013-09-01T00_00_00Z.png", _random_rgb(rng))
    _save(tmp_path / "snapshot-2013-09-02T00_00_00Z.png", _random_rgb(rng, (NY, NX + 1)))
    with pytest.raises(DataError) as info:
        open_image_stack(tmp_path, BBOX)
    msg = str(info.value)
    assert "2013-09-01" in msg and "2013-09-02" in msg
    assert f"{NY} x {NX}" in msg and f"{NY} x {NX + 1}" in msg


def test_corrupt_and_truncated_images(tmp_path):
    rng = np.random.default_rng(0)
    _save(tmp_path / "snapshot-2013-09-01T00_00_00Z.png", _random_rgb(rng))
    garbage = tmp_path / "snapshot-2013-09-02T00_00_00Z.png"
    garbage.write_bytes(b"this is not a PNG file at all")
    with pytest.raises(DataError, match="snapshot-2013-09-02"):
        open_image_stack(tmp_path, BBOX)
    good = (tmp_path / "snapshot-2013-09-01T00_00_00Z.png").read_bytes()
    garbage.write_bytes(good[: len(good) // 2])  # valid header, truncated data
    with pytest.raises(DataError, match="snapshot-2013-09-02"):
        open_image_stack(tmp_path, BBOX)


def test_grayscale_images_are_refused(tmp_path):
    Image.fromarray(np.full((NY, NX), 100, np.uint8)).save(tmp_path / "g_2014-01-01.png")
    with pytest.raises(DataError, match="grayscale"):
        open_image_stack(tmp_path, BBOX)


def test_empty_folder_missing_path_and_no_glob_match(tmp_path):
    with pytest.raises(DataError, match="no image"):
        open_image_stack(tmp_path, BBOX)
    (tmp_path / "readme.txt").write_text("x")
    with pytest.raises(DataError, match="no image"):
        open_image_stack(tmp_path, BBOX)
    with pytest.raises(DataError, match="not found"):
        open_image_stack(tmp_path / "missing", BBOX)
    with pytest.raises(DataError, match="no file matches"):
        open_image_stack(str(tmp_path / "*.png"), BBOX)
    with pytest.raises(DataError):
        open_image_stack([], BBOX)


@pytest.mark.parametrize("bbox", [
    (48.0, -80.0, 40.0, -68.0),  # south > north
    (40.0, -80.0, 40.0, -68.0),  # south == north
    (40.0, -68.0, 48.0, -80.0),  # west > east
    (40.0, -80.0, 48.0),  # too short
    (-95.0, -80.0, 48.0, -68.0),  # south < -90
    (40.0, -80.0, float("nan"), -68.0),
    "40,-80,48,-68",
])
def test_invalid_bbox(tmp_path, bbox):
    _save(tmp_path / "s_2014-01-01.png", _random_rgb(np.random.default_rng(0)))
    with pytest.raises(RegionError, match="bbox"):
        open_image_stack(tmp_path, bbox)


def test_invalid_thresholds(tmp_path):
    _save(tmp_path / "s_2014-01-01.png", _random_rgb(np.random.default_rng(0)))
    for kwargs in ({"saturation_min": 1.5}, {"value_max": -0.1}, {"dark_max": "x"},
                   {"edge_sigma": 0}, {"edge_low": 0.3, "edge_high": 0.2},
                   {"edge_dilate": 1.5}, {"edge_dilate": -1}):
        with pytest.raises(DataError, match=next(iter(kwargs)).split("_")[0]):
            open_image_stack(tmp_path, BBOX, **kwargs)


# --------------------------------------------------------------------------- writing
def _field(n=4, missing=0.3, seed=1):
    return synthetic_field(n, (NY, NX), missing=missing, seed=seed,
                           lat_range=(40.0, 48.0), lon_range=(-80.0, -68.0))


def test_write_names_and_exact_colours(tmp_path):
    field = _field(3)
    field[0, 0, 0] = -1.0
    field[0, 0, 1] = 1.0
    field[0, 0, 2] = 5.0  # clipped to vmax
    field[0, 0, 3] = np.nan
    paths = write_image_stack(tmp_path, field, vmin=-1.0, vmax=1.0)
    assert [p.name for p in paths] == [f"snapshot-2013-01-0{i}T00_00_00Z.png" for i in (1, 2, 3)]
    assert sorted(tmp_path.iterdir()) == paths  # no temporary files left
    img = np.asarray(Image.open(paths[0]))
    assert img.shape == (NY, NX, 3) and img.dtype == np.uint8
    assert tuple(img[0, 0]) == (204, 0, 0)  # hue 0, v = 0.8
    assert tuple(img[0, 1]) == (204, 0, 204)  # hue 300
    assert tuple(img[0, 2]) == (204, 0, 204)
    assert tuple(img[0, 3]) == (255, 255, 255)  # NaN -> white cloud
    nan = np.isnan(field.values[0])
    assert (img[nan] == 255).all() and not (img[~nan] == 255).any()
    # every finite pixel has s = 1 and v = 0.8
    hsv = rgb2hsv(img)
    np.testing.assert_allclose(hsv[~nan][:, 1], 1.0)
    np.testing.assert_allclose(hsv[~nan][:, 2], 0.8)


@pytest.mark.parametrize("fmt, start_hue, hue_span", [
    ("png", 0.0, 300.0), ("tif", 120.0, -120.0), ("png", 200.0, 330.0)])
def test_round_trip_recovers_field(tmp_path, fmt, start_hue, hue_span):
    field = _field()
    vmin, vmax = float(field.min()), float(field.max())
    write_image_stack(tmp_path, field, fmt=fmt, start_hue=start_hue, hue_span=hue_span)
    hue = open_image_stack(tmp_path, field_bbox(field), edge_sigma=None)
    np.testing.assert_allclose(hue["lat"], field["lat"])
    np.testing.assert_allclose(hue["lon"], field["lon"])
    np.testing.assert_array_equal(hue["time"], field["time"])
    back = hue_to_value(hue, vmin, vmax, start_hue=start_hue, hue_span=hue_span)
    assert isinstance(back, xr.DataArray)
    np.testing.assert_array_equal(np.isnan(back.values), np.isnan(field.values))
    # 8-bit quantisation: the mid channel is off by <= 0.5/204 of a 60-degree sextant
    tol = 60.0 * 0.5 / 204.0 / abs(hue_span) * (vmax - vmin) * 1.01
    err = np.abs(back.values - field.values)
    assert np.nanmax(err) <= tol


def test_round_trip_with_edge_masking_on(tmp_path):
    field = synthetic_field(3, (NY, NX), missing=0.0, land_fraction=1.0, seed=4)
    field[:, 10:20, 12:27] = np.nan  # a cloud
    field[1, 25:32, 40:50] = np.nan
    vmin, vmax = float(field.min()), float(field.max())
    write_image_stack(tmp_path, field)
    hue = open_image_stack(tmp_path, field_bbox(field))
    nan_in = np.isnan(field.values)
    nan_out = np.isnan(hue.values)
    assert (nan_out >= nan_in).all()  # clouds and land mask stay masked
    back = hue_to_value(hue.values, vmin, vmax)
    tol = 60.0 * 0.5 / 204.0 / 300.0 * (vmax - vmin) * 1.01
    assert np.nanmax(np.abs(back - field.values)) <= tol
    # away from NaN borders the data survive
    for t in range(3):
        far = distance_transform_edt(~nan_in[t]) > 8
        far[:3] = far[-3:] = False
        far[:, :3] = far[:, -3:] = False
        assert far.any() and not nan_out[t][far].any()


def test_round_trip_ascending_lat_is_flipped(tmp_path):
    field = _field(2)
    up = field.isel(lat=slice(None, None, -1))
    write_image_stack(tmp_path / "a", field)
    write_image_stack(tmp_path / "b", up)
    for a, b in zip(sorted((tmp_path / "a").iterdir()), sorted((tmp_path / "b").iterdir()),
                    strict=True):
        np.testing.assert_array_equal(np.asarray(Image.open(a)), np.asarray(Image.open(b)))
    hue = open_image_stack(tmp_path / "b", field_bbox(up), edge_sigma=None)
    np.testing.assert_allclose(hue["lat"], field["lat"])


def test_jpeg_round_trip_loosely(tmp_path):
    field = _field(2, missing=0.0)
    vmin, vmax = float(field.min()), float(field.max())
    paths = write_image_stack(tmp_path, field, fmt="jpg")
    assert all(p.suffix == ".jpg" for p in paths)
    hue = open_image_stack(tmp_path, field_bbox(field), edge_sigma=None)
    back = hue_to_value(hue.values, vmin, vmax)
    for t in range(2):
        inner = distance_transform_edt(np.isfinite(field.values[t])) > 3
        err = np.abs(back[t][inner] - field.values[t][inner]) / (vmax - vmin)
        assert np.isfinite(err).all()
        assert np.median(err) < 0.01 and np.quantile(err, 0.95) < 0.05


def test_write_errors(tmp_path):
    field = _field(2)
    with pytest.raises(DataError, match="fmt"):
        write_image_stack(tmp_path, field, fmt="gif")
    with pytest.raises(DataError, match="vmin < vmax"):
        write_image_stack(tmp_path, field, vmin=1.0, vmax=0.0)
    with pytest.raises(DataError, match="hue_span"):
        write_image_stack(tmp_path, field, hue_span=360.0)
    with pytest.raises(DataError, match="time"):
        write_image_stack(tmp_path, field.isel(time=0))
    with pytest.raises(DataError, match="all NaN"):
        write_image_stack(tmp_path, field * np.nan)
    with pytest.raises(FileExistsError):
        write_image_stack(tmp_path, field)
        write_image_stack(tmp_path, field, overwrite=False)


def test_hue_to_value_wraps_just_below_start():
    hue = np.array([0.0, 150.0, 300.0, 359.9, 330.1, 329.9])
    got = hue_to_value(hue, 0.0, 300.0)
    np.testing.assert_allclose(got, [0.0, 150.0, 300.0, -0.1, -29.9, 329.9], atol=1e-9)
    got = hue_to_value(np.array([120.0, 60.0, 0.0, 121.0]), 0.0, 1.0, start_hue=120.0,
                       hue_span=-120.0)
    np.testing.assert_allclose(got, [0.0, 0.5, 1.0, -1.0 / 120.0])


def test_field_bbox_matches_grid():
    field = _field(1)
    assert field_bbox(field) == pytest.approx((40.0, -80.0, 48.0, -68.0))
