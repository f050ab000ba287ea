"""Remote reading over real loopback servers: HTTP with Range (standard library) and S3 (moto).

Each server binds 127.0.0.1 on a free port, is started and stopped by a fixture, and counts
what it sends, so "reads only the chunks covering the bbox" is measured, not assumed.
"""

from __future__ import annotations

import http.server as http_server_lib
import os
import re
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import xarray as xr

pytest.importorskip("fsspec")
pytest.importorskip("aiohttp")
pytest.importorskip("h5netcdf")

from lrm_cvx.errors import DataError  # noqa: E402
from lrm_cvx.io import open_data  # noqa: E402
from lrm_cvx.io.ndvi import open_ndvi_cdr, write_ndvi_cdr  # noqa: E402
from lrm_cvx.io.samples import synthetic_field  # noqa: E402

BBOX = (40.0, 10.0, 42.0, 12.0)  # 2 x 2 degrees


# ------------------------------------------------------------------------------ HTTP server
class _State:
    """What the HTTP server sent and how it misbehaves (set by a test, reset by the fixture)."""

    def __init__(self, root: Path):
        self.root = root
        self.reset()

    def reset(self) -> None:
        self.lock = threading.Lock()
        self.body_bytes: dict[str, int] = {}
        self.requests: list[tuple[str, str, str | None]] = []
        self.drop_after: int | None = None  # close the connection after this many body bytes
        self.drop_from = 0                   # ... in GET responses from this one on (0-based)
        self.stall = None                    # an Event: GET bodies wait for it before sending
        self.gets = 0
        self.fail_status: int | None = None  # answer this status ...
        self.fail_times = 0                  # ... to this many GET requests, then serve
        self.ignore_range = False            # a server without Range support: always 200


class _RangeHandler(http_server_lib.SimpleHTTPRequestHandler):
    """Serves ``state.root`` honouring ``Range: bytes=a-b`` and counting body bytes per file."""

    protocol_version = "HTTP/1.1"
    state: _State

    def __init__(self, *args, **kwargs):
        super().__init__(*args, directory=str(self.state.root), **kwargs)

    def log_message(self, *args) -> None:  # keep test output quiet
        pass

    def _file(self) -> Path | None:
        path = Path(self.translate_path(self.path))
        return path if path.is_file() else None

    def do_HEAD(self) -> None:
        self._serve(head=True)

    def do_GET(self) -> None:
        self._serve(head=False)

    def _serve(self, head: bool) -> None:
        st = self.state
        with st.lock:
            st.requests.append((self.command, self.path, self.headers.get("Range")))
            fail = not head and st.fail_times > 0 and st.fail_status is not None
            if fail:
                st.fail_times -= 1
            drop = (not head and st.drop_after is not None and st.gets >= st.drop_from)
            st.gets += not head
        if fail:
            self.send_error(st.fail_status)
            return
        path = self._file()
        if path is None:
            return super().do_HEAD() if head else super().do_GET()  # 404 or a folder listing
        data = path.read_bytes()
        size = len(data)
        rng = None if st.ignore_range else self.headers.get("Range")
        start, end = 0, size - 1
        if rng:
            m = re.fullmatch(r"bytes=(\d*)-(\d*)", rng.strip())
            if m is None:
                self.send_error(416)
                return
            if m[1]:
                start = int(m[1])
                end = min(int(m[2]), size - 1) if m[2] else size - 1
            else:
                start, end = max(size - int(m[2]), 0), size - 1
            if start >= size or start > end:
                self.send_response(416)
                self.send_header("Content-Range", f"bytes */{size}")
                self.send_header("Content-Length", "0")
                self.end_headers()
                return
            self.send_response(206)
            self.send_header("Content-Range", f"bytes {start}-{end}/{size}")
        else:
            self.send_response(200)
        body = data[start:end + 1]
        self.send_header("Content-Type", "application/x-netcdf")
        self.send_header("Accept-Ranges", "bytes")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        if head:
            return
        if st.stall is not None and not head:
            st.stall.wait(timeout=10)  # released by the test (bounded anyway)
        if drop:
            body = body[: st.drop_after]
            self.close_connection = True
        self.wfile.write(body)
        self.wfile.flush()
        with st.lock:
            st.body_bytes[path.name] = st.body_bytes.get(path.name, 0) + len(body)
        if drop:
            self.connection.shutdown(2)


@pytest.fixture(scope="module")
def http_server(tmp_path_factory):
    root = tmp_path_factory.mktemp("www")
    state = _State(root)
    handler = type("Handler", (_RangeHandler,), {"state": state})
    server = http_server_lib.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05},
                              daemon=True)
    thread.start()
    state.url = f"http://127.0.0.1:{server.server_address[1]}"
    try:
        yield state
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=5)


@pytest.fixture
def http(http_server):
    http_server.reset()
    yield http_server
    http_server.reset()


@pytest.fixture(autouse=True)
def _no_env_cache(monkeypatch):
    monkeypatch.delenv("LRM_CVX_CACHE", raising=False)
    monkeypatch.setenv("NO_PROXY", "127.0.0.1,localhost")  # loopback never via a proxy
    monkeypatch.setenv("no_proxy", "127.0.0.1,localhost")
    monkeypatch.setattr("lrm_cvx.io.remote.BACKOFF", 0.01)


# ------------------------------------------------------------------------------ data
def small_field(n=2, seed=0):
    f = synthetic_field(n, (24, 32), missing=0.2, land_fraction=0.9, seed=seed,
                        lat_range=(36.0, 47.5), lon_range=(4.0, 19.5))
    return f.clip(-0.09, 1.0)


def global_field(seed=0):
    """One day on a global grid like the CDR's (0.05 degree, 3600 x 7200) at half the
    resolution (0.1 degree, 1800 x 3600) to keep the test fast: smooth plus noise, so zlib
    chunks stay real (~40% of the raw bytes)."""
    lat = (90 - 0.05 - 0.1 * np.arange(1800)).astype(np.float32)
    lon = (-180 + 0.05 + 0.1 * np.arange(3600)).astype(np.float32)
    rng = np.random.default_rng(seed)
    a = (0.3 * np.cos(np.radians(lat))).astype(np.float32)
    b = np.sin(np.radians(2 * lon)).astype(np.float32)
    values = rng.integers(-60, 60, size=(1800, 3600), dtype=np.int16).astype(np.float32)
    values *= np.float32(1e-4)
    values += np.float32(0.4) + a[:, None] * b[None]
    return xr.DataArray(values[None], dims=("time", "lat", "lon"),
                        coords={"time": pd.to_datetime(["2001-06-01"]), "lat": lat, "lon": lon})


@pytest.fixture(scope="module")
def global_files(http_server):
    """The same global day tiled 600 x 600 (zlib) and contiguous, on the HTTP server."""
    root = http_server.root
    f = global_field()
    tiled = write_ndvi_cdr(root / "tiled", f, chunks=(600, 600), complevel=1)[0]
    flat = write_ndvi_cdr(root / "flat", f, chunks=None)[0]
    return {"tiled": tiled, "flat": flat}


def url_of(state: _State, path: Path) -> str:
    return f"{state.url}/{path.relative_to(state.root).as_posix()}"


def assert_same(a: xr.DataArray, b: xr.DataArray) -> None:
    xr.testing.assert_identical(a, b)
    np.testing.assert_array_equal(a.values, b.values)
    for name in a.coords:
        assert a[name].attrs == b[name].attrs
    assert a.attrs == b.attrs


# ------------------------------------------------------------------------------ HTTP tests
def test_http_window_equals_local_and_reads_few_bytes(http, global_files):
    path = global_files["tiled"]
    local = open_ndvi_cdr(path, bbox=BBOX)
    remote = open_ndvi_cdr(url_of(http, path), bbox=BBOX)
    assert_same(remote, local)
    assert remote.shape == (1, 20, 20)
    sent = http.body_bytes[path.name]
    fraction = sent / path.stat().st_size
    print(f"\ntiled 600x600 file of {path.stat().st_size} bytes: sent {sent} bytes "
          f"({100 * fraction:.2f}%) in {len(http.requests)} requests for a 2x2 degree window")
    assert fraction <= 0.15
    assert all(method == "HEAD" or rng for method, _, rng in http.requests)  # never whole


def test_http_untiled_file_reads_correctly(http, global_files):
    path = global_files["flat"]
    local = open_ndvi_cdr(path, bbox=BBOX)
    assert_same(open_ndvi_cdr(url_of(http, path), bbox=BBOX), local)
    assert http.body_bytes[path.name] < path.stat().st_size  # still ranged rows, not all


def test_http_list_glob_folder_and_open_data(http, tmp_path):
    folder = http.root / "days"
    paths = write_ndvi_cdr(folder, small_field(n=2))
    local = open_ndvi_cdr(paths, bbox=BBOX)
    urls = [url_of(http, p) for p in paths]
    lazy = open_ndvi_cdr(urls[::-1], bbox=BBOX, chunks={"time": 1, "latitude": 2})
    assert lazy.chunks is not None and lazy.chunks[1][0] == 2
    assert_same(lazy.compute(), local)  # sorted by date, chunked like a local read
    assert_same(open_ndvi_cdr(f"{http.url}/days/AVHRR-*.nc", bbox=BBOX), local)
    assert_same(open_data(f"{http.url}/days/", bbox=BBOX), open_data(paths, bbox=BBOX))
    with pytest.raises(DataError, match=r"no file matches .*days/VIIRS-\*\.nc"):
        open_ndvi_cdr(f"{http.url}/days/VIIRS-*.nc")


def test_http_generic_netcdf(http):
    f = small_field(n=3).rename("sst")
    f.attrs["units"] = "K"
    (http.root / "generic").mkdir(exist_ok=True)
    f.to_netcdf(http.root / "generic" / "a.nc", engine="netcdf4")
    f.to_netcdf(http.root / "generic" / "b3.nc", engine="scipy")  # NetCDF-3
    local = open_data(http.root / "generic" / "a.nc", bbox=BBOX)
    assert_same(open_data(f"{http.url}/generic/a.nc", bbox=BBOX), local)
    assert_same(open_data(f"{http.url}/generic/b3.nc", bbox=BBOX), local)


def test_http_404_is_data_error_naming_url(http):
    url = f"{http.url}/nowhere/AVHRR-Land_v005_AVH13C1_NOAA-19_20010601_c20240101000000.nc"
    with pytest.raises(DataError, match=re.escape(url) + r".*404"):
        open_ndvi_cdr(url)


@pytest.mark.parametrize("drop_from", [0, 1])  # at the first request / after the metadata
def test_http_dropped_connection_is_data_error_after_bounded_retries(http, global_files,
                                                                     drop_from):
    path = global_files["tiled"]
    http.drop_after, http.drop_from = 100, drop_from  # responses cut after 100 body bytes
    with pytest.raises(DataError, match=re.escape(url_of(http, path)) + ".*dropped.*4 attempts"):
        open_ndvi_cdr(url_of(http, path), bbox=BBOX)
    # the first try (with its 1-byte Range probe of the file's end, which succeeds once the
    # metadata did) and RETRIES=3 more, each stopped early
    assert http.gets <= 4 + 2 * drop_from


def test_http_stalled_server_times_out_after_bounded_retries(http, global_files,
                                                            monkeypatch):
    path = global_files["tiled"]
    monkeypatch.setattr("lrm_cvx.io.remote.READ_TIMEOUT", 0.2)
    http.stall = threading.Event()
    try:
        with pytest.raises(DataError, match=re.escape(url_of(http, path)) +
                           ".*timed out.*after 4 attempts"):
            open_ndvi_cdr(url_of(http, path), bbox=BBOX)
    finally:
        http.stall.set()
    assert http.gets == 4


def test_http_transient_5xx_is_retried(http, global_files):
    path = global_files["tiled"]
    http.fail_status, http.fail_times = 503, 2
    local = open_ndvi_cdr(path, bbox=BBOX)
    assert_same(open_ndvi_cdr(url_of(http, path), bbox=BBOX), local)
    assert http.fail_times == 0
    http.reset()
    http.fail_status, http.fail_times = 500, 100  # never recovers
    with pytest.raises(DataError, match=r"HTTP status 500 after 4 attempts"):
        open_ndvi_cdr(url_of(http, path), bbox=BBOX)


def test_refused_connection_is_data_error():
    import socket

    with socket.socket() as s:  # a free port with nobody listening
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    url = f"http://127.0.0.1:{port}/AVHRR-Land_v005_AVH13C1_NOAA-19_20010601_c20240101000000.nc"
    with pytest.raises(DataError, match=re.escape(url) + ".*(refused|404)"):
        open_ndvi_cdr(url)


def test_block_cache_serves_second_read_without_server(http, global_files, tmp_path):
    path = global_files["tiled"]
    url = url_of(http, path)
    first = open_ndvi_cdr(url, bbox=BBOX, cache=tmp_path / "cache")
    sent = http.body_bytes[path.name]
    assert sent <= 0.15 * path.stat().st_size  # the cache keeps partial reads partial
    http.reset()
    second = open_ndvi_cdr(url, bbox=BBOX, cache=tmp_path / "cache")
    assert http.requests == []
    assert_same(second, first)
    cached = sum(f.stat().st_blocks * 512 for f in (tmp_path / "cache").iterdir())
    assert cached <= 2 * sent + 2**20  # a sparse file of the blocks read, not the whole file


# ------------------------------------------------------------------------------ S3 (moto)
@pytest.fixture(scope="module")
def s3_server():
    pytest.importorskip("s3fs")
    moto_server = pytest.importorskip("moto.server")
    boto3 = pytest.importorskip("boto3")
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    try:
        host, port = server.get_host_and_port()
        endpoint = f"http://{host}:{port}"
        client = boto3.client("s3", endpoint_url=endpoint, region_name="us-east-1",
                              aws_access_key_id="testing", aws_secret_access_key="testing")
        client.create_bucket(Bucket="noaa-cdr-ndvi-pds", ACL="public-read")  # as NOAA's
        yield endpoint, client
    finally:
        server.stop()


def test_s3_glob_window_equals_local(s3_server, tmp_path, monkeypatch):
    endpoint, client = s3_server
    for k in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_PROFILE", "AWS_ENDPOINT_URL"):
        monkeypatch.delenv(k, raising=False)
    paths = write_ndvi_cdr(tmp_path, small_field(n=3), chunks=(8, 8))
    for p in paths:
        client.upload_file(str(p), "noaa-cdr-ndvi-pds", f"data/2001/{p.name}",
                           ExtraArgs={"ACL": "public-read"})
    local = open_ndvi_cdr(paths, bbox=BBOX)
    opts = {"endpoint_url": endpoint}
    got = open_ndvi_cdr("s3://noaa-cdr-ndvi-pds/data/2001/AVHRR-*.nc", bbox=BBOX,
                        storage_options=opts)  # anonymous by default
    assert_same(got, local)
    one = f"s3://noaa-cdr-ndvi-pds/data/2001/{paths[1].name}"
    local_one = open_ndvi_cdr(paths[1], bbox=BBOX)
    assert_same(open_data([one], bbox=BBOX, storage_options=opts), local_one)
    monkeypatch.setenv("AWS_ENDPOINT_URL", endpoint)  # the environment works as well
    assert_same(open_ndvi_cdr(one, bbox=BBOX), local_one)
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")  # credentials in the environment:
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")  # signed requests
    assert_same(open_ndvi_cdr(one, bbox=BBOX), local_one)
    with pytest.raises(DataError, match=r"s3://noaa-cdr-ndvi-pds/data/1999/AVHRR.*404"):
        open_ndvi_cdr("s3://noaa-cdr-ndvi-pds/data/1999/"
                      "AVHRR-Land_v005_AVH13C1_NOAA-14_19990101_c20240101000000.nc",
                      storage_options=opts)


# ------------------------------------------------------------------------------ CLI
def test_cli_fit_reads_a_url(http, tmp_path):
    from lrm_cvx.cli import main

    folder = http.root / "cli"
    write_ndvi_cdr(folder, small_field(n=6, seed=3))
    out = tmp_path / "model.nc"
    code = main(["fit", f"{http.url}/cli/AVHRR-*.nc", "--bbox", "36,4,47.5,19.5",
                 "--rank", "2", "--max-iter", "3", "-q", "-o", str(out)])
    assert code in (0, None) and out.exists()
    assert os.path.getsize(out) > 0


# ------------------------------------------------------- a server without Range
@pytest.fixture
def no_range_file(http):
    """A 0.5 MB NetCDF-4 file (larger than one block) served without Range support."""
    rng = np.random.default_rng(0)
    da = xr.DataArray(rng.normal(size=(20, 60, 100)).astype(np.float32), name="v",
                      dims=("time", "lat", "lon"),
                      coords={"time": pd.date_range("2000", periods=20), "lat":
                              np.linspace(-30, 30, 60), "lon": np.linspace(0, 80, 100)})
    path = http.root / "norange.nc"
    da.to_netcdf(path, engine="netcdf4")
    assert path.stat().st_size > 2 * 128 * 1024
    http.ignore_range = True
    return url_of(http, path)


def test_a_server_without_range_support_is_one_clear_error(no_range_file, tmp_path):
    with pytest.raises(DataError, match="does not support HTTP Range requests"):
        open_data(no_range_file)
    for cache in (None, tmp_path / "cache", tmp_path / "cache"):  # twice: no poisoned cache
        with pytest.raises(DataError, match="does not support HTTP Range requests"):
            open_data(no_range_file, cache=cache)


def test_cli_exits_2_cleanly_after_a_server_without_range(no_range_file, tmp_path):
    # the crash: the one-line error, then SIGSEGV at exit (139); the exit status is 2
    env = dict(os.environ, LRM_CVX_CACHE=str(tmp_path / "cache"))
    for _ in range(2):
        proc = subprocess.run([sys.executable, "-m", "lrm_cvx.cli", "-q", "fit", no_range_file,
                               "-o", str(tmp_path / "m.nc")], capture_output=True, text=True,
                              timeout=300, env=env)
        assert proc.returncode == 2, (proc.returncode, proc.stderr)
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and "does not support HTTP Range requests" in lines[0]
    assert not (tmp_path / "m.nc").exists()


def test_cli_exits_2_when_the_connection_drops_inside_h5py(http, global_files, tmp_path):
    # the metadata and the range probe arrive, then h5py's next read is cut: HDF5 keeps the
    # file-object driver's property list, whose release at exit crashed the process (139)
    path = global_files["tiled"]
    http.drop_after, http.drop_from = 100, 2
    proc = subprocess.run([sys.executable, "-m", "lrm_cvx.cli", "-q", "fit", url_of(http, path),
                           "-o", str(tmp_path / "m.nc")], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "dropped" in lines[0], proc.stderr
