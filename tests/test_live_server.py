"""The live page's server (live/server.py) against a stub state: which requests it answers
(DNS rebinding: only its loopback names, no other web page's origin) and ``/events``' Last-Event-ID."""
import http.client
import json
from dataclasses import dataclass, field

import pytest

from mirror_fg.live.server import LiveServer


@dataclass
class StubState:
    seq: int = 5
    status: dict = field(default_factory=lambda: {"frame": 12, "status": "added", "placements": 3})
    jpeg: bytes = b"\xff\xd8 not really a picture \xff\xd9"


@pytest.fixture()
def server():
    state = StubState()
    live = LiveServer(0, lambda: state)
    live.start()
    yield live
    live.stop()


def get(server: LiveServer, path: str, headers: dict | None = None) -> tuple[int, bytes]:
    connection = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
    try:
        connection.request("GET", path, headers={"Host": f"127.0.0.1:{server.port}", **(headers or {})})
        response = connection.getresponse()
        return response.status, response.read()
    finally:
        connection.close()


ROUTES = ["/", "/events", "/frame.jpg", "/nothing-here"]


@pytest.mark.parametrize("path", ROUTES)
@pytest.mark.parametrize("host", ["evil.example", "evil.example:{port}", "127.0.0.1", "127.0.0.1:1",
                                  "localhost.evil.example:{port}", "127.0.0.2:{port}", ""])
def test_a_foreign_host_is_refused_on_every_route(server, path, host):
    status, body = get(server, path, {"Host": host.format(port=server.port)})
    assert status == 421
    assert b"data:" not in body and b"not really a picture" not in body and b"<html" not in body


@pytest.mark.parametrize("path", ROUTES)
@pytest.mark.parametrize("origin", ["http://evil.example", "http://evil.example:{port}", "null",
                                    "https://127.0.0.1:{port}", "http://127.0.0.1:1"])
def test_a_foreign_origin_is_refused_on_every_route(server, path, origin):
    status, body = get(server, path, {"Origin": origin.format(port=server.port)})
    assert status == 403
    assert b"data:" not in body and b"not really a picture" not in body and b"<html" not in body


@pytest.mark.parametrize("host", ["127.0.0.1:{port}", "localhost:{port}", "LOCALHOST:{port}", "[::1]:{port}"])
def test_the_loopback_names_are_served(server, host):
    host = host.format(port=server.port)
    status, body = get(server, "/events", {"Host": host, "Origin": f"http://{host}"})
    assert status == 200 and b"data:" in body
    assert get(server, "/frame.jpg", {"Host": host})[0] == 200
    status, page = get(server, "/", {"Host": host})
    assert status == 200 and b"<html" in page
    assert get(server, "/nothing-here", {"Host": host})[0] == 404


def test_events_send_a_state_once_by_its_last_event_id(server):
    status, body = get(server, "/events")  # a new client: the current state
    lines = body.decode().splitlines()
    assert status == 200 and "id: 5" in lines
    assert json.loads(next(line for line in lines if line.startswith("data: "))[6:])["frame"] == 12
    status, body = get(server, "/events", {"Last-Event-ID": "5"})  # it has seen seq 5: nothing new
    assert status == 200 and not any(line.startswith("data:") for line in body.decode().splitlines())
    status, body = get(server, "/events", {"Last-Event-ID": "4"})  # an older one: seq 5 again
    assert status == 200 and "id: 5" in body.decode().splitlines()
