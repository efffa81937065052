"""``dask_address`` at something that is not a Dask scheduler: one line naming it, within 30 s."""

from __future__ import annotations

import asyncio
import http.server
import socket
import threading
import time

import pytest
from photonpano.dask_probe import check_scheduler
from robust import TINY, assert_one_line_error, run_subprocess

pytest.importorskip("distributed")


@pytest.fixture
def http_server():
    """A local web server (it waits for a request: a Dask client waiting for a handshake would hang)."""
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"tcp://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()


@pytest.fixture
def chatty_server():
    """A TCP server that greets each connection in HTTP (read as a Dask frame length: 3.07 EiB)."""
    listener = socket.create_server(("127.0.0.1", 0))
    stop = threading.Event()

    def serve():
        listener.settimeout(0.2)
        while not stop.is_set():
            try:
                conn, _ = listener.accept()
            except OSError:
                continue
            with conn:
                conn.sendall(b"HTTP/1.0 200 OK\r\nContent-Length: 0\r\n\r\n")
                time.sleep(0.5)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    yield f"tcp://127.0.0.1:{listener.getsockname()[1]}"
    stop.set()
    thread.join()
    listener.close()


def _run_dask(tmp_path, address):
    start = time.perf_counter()
    result = run_subprocess("demo", "-o", tmp_path / "out", *TINY, "--set", "executor=dask", "--set",
                            f"dask_address={address}", timeout=60)
    return result, time.perf_counter() - start


def test_a_server_speaking_first_in_another_protocol_is_refused_at_once(tmp_path, chatty_server):
    result, seconds = _run_dask(tmp_path, chatty_server)
    line = assert_one_line_error(result, "dask_address", f"{chatty_server!r} is not a Dask scheduler")
    assert "HTTP/1.0" in line and "EiB" not in line
    assert seconds < 30 and not (tmp_path / "out").exists()  # the command, start-up and capture included
    start = time.perf_counter()  # "at once": the probe itself does not wait out its 10 s timeout
    with pytest.raises(Exception, match="not a Dask scheduler"):
        check_scheduler(chatty_server, 10.0)
    assert time.perf_counter() - start < 2


@pytest.mark.slow
def test_a_web_server_is_refused_within_30_s(tmp_path, http_server):
    result, seconds = _run_dask(tmp_path, http_server)
    assert_one_line_error(result, "dask_address", f"{http_server!r} is not a Dask scheduler", "within 10 s")
    assert seconds < 30 and not (tmp_path / "out").exists()


@pytest.mark.slow
def test_an_unroutable_address_is_refused_within_30_s(tmp_path):
    address = "tcp://10.255.255.1:8786"  # no route (a sandbox's proxy may accept, then reset or stay silent)
    result, seconds = _run_dask(tmp_path, address)
    line = assert_one_line_error(result, "dask_address", repr(address))
    assert "EiB" not in line and seconds < 30


def test_a_closed_port_is_refused_in_one_line(tmp_path):
    with socket.create_server(("127.0.0.1", 0)) as free:
        port = free.getsockname()[1]  # closed again below: nothing listens there
    result, seconds = _run_dask(tmp_path, f"tcp://127.0.0.1:{port}")
    assert_one_line_error(result, f"tcp://127.0.0.1:{port}", "no Dask scheduler answers")
    assert seconds < 10


def test_a_real_scheduler_passes_the_check():
    from distributed import Scheduler

    async def probe():
        async with Scheduler(host="127.0.0.1", port=0, dashboard_address=None) as scheduler:
            start = time.perf_counter()
            await asyncio.get_running_loop().run_in_executor(None, check_scheduler, scheduler.address, 5.0)
            return time.perf_counter() - start

    assert asyncio.run(probe()) < 2
