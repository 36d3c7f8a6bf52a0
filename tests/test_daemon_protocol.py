"""The control protocol's parser and the socket server's framing, limits and peer check."""

from __future__ import annotations

import json
import os
import socket
import tempfile
import threading
from pathlib import Path

import pytest

from flgd.daemon.protocol import COMMANDS, MAX_REQUEST_BYTES, ProtocolError, Request, parse_request
from flgd.daemon.server import ControlServer, PeerPolicy, SocketInUse
from tests.fakes.daemon import read_line


@pytest.mark.parametrize("line, code", [
    (b"", "bad_request"),
    (b"   ", "bad_request"),
    (b"\xff\xfe", "bad_request"),
    (b"{not json", "bad_request"),
    (b"[1, 2]", "bad_request"),
    (b'"status"', "bad_request"),
    (b'{"cmd": 5}', "bad_request"),
    (b'{"cmd": "dance"}', "unknown_command"),
    (b'{"cmd": "status", "args": [1]}', "bad_request"),
    (b'{"cmd": "status", "args": {"x": 1}}', "bad_request"),
    (b'{"cmd": "backend"}', "bad_request"),
    (b'{"cmd": "backend", "args": {"name": 3}}', "bad_request"),
    (b'{"cmd": "policy_load", "args": {"path": true}}', "bad_request"),
    (b'{"cmd": "status", "id": {"a": 1}}', "bad_request"),
    (b'{"cmd": "status", "extra": 1}', "bad_request"),
    (b"[" * 100000, "too_long"),
    (b"[" * 5000 + b"]" * 5000, "bad_request"),  # deep nesting: a clean error, not a RecursionError
])
def test_bad_requests_are_classified(line, code):
    with pytest.raises(ProtocolError) as err:
        parse_request(line)
    assert err.value.code == code
    assert err.value.message


@pytest.mark.parametrize("line, says", [
    (b'{"cmd": "status", "cmd": "stop"}', "key 'cmd' appears twice"),
    (b'{"cmd": "backend", "args": {"name": "sim", "name": "ur5e"}}', "key 'name' appears twice"),
    (b'{"cmd": "policy_load", "args": {"path": "/var/lib/flgd/a\\u0000b.flgp"}}', "contains a NUL character"),
    (b'{"cmd": "status", "id": ' + b"7" * 4300 + b"}", "'id' is a 4300-digit number"),
    (b'{"cmd": "policy_history", "args": {"limit": ' + b"9" * 4000 + b"}}", "'limit' is a 4000-digit number"),
    (b'{"cmd": "status", "id": "' + b"x" * 5000 + b'"}', "'id' is a string of 5000 characters"),
])
def test_ambiguous_or_oversized_values_are_refused_by_name_and_never_quoted_back_whole(line, says):
    with pytest.raises(ProtocolError) as err:
        parse_request(line)
    assert err.value.code == "bad_request" and says in err.value.message
    assert len(err.value.message) < 200


def test_valid_requests_parse():
    assert parse_request(b'{"cmd": "status"}') == Request("status", {}, None)
    r = parse_request(b'{"cmd": "backend", "args": {"name": "sim"}, "id": 7}')
    assert (r.cmd, r.args, r.id) == ("backend", {"name": "sim"}, 7)
    assert parse_request(b'{"cmd": "policy_save", "args": null}').args == {}
    assert set(COMMANDS) >= {"start", "pause", "reset", "status", "stats", "stop", "policy_load", "policy_save",
                             "backend", "snapshot"}


def test_every_protocol_command_has_one_handler_and_every_handler_a_protocol_command():
    from flgd.daemon.commands import HANDLERS

    assert set(HANDLERS) == set(COMMANDS)


@pytest.fixture
def server(tmp_path):
    seen: list[Request] = []

    def handler(req: Request) -> dict:
        seen.append(req)
        if req.cmd == "stop":
            raise ProtocolError("wrong_state", "not now")
        if req.cmd == "reset":
            raise RuntimeError("handler bug")
        return {"echo": req.cmd, "nan": float("nan")}

    srv = ControlServer(tmp_path / "s" / "ctl.sock", handler, lambda: "IDLE", PeerPolicy(None))
    srv.start()
    srv.seen = seen
    yield srv
    srv.stop()


NL = b"\n"


def _lines(sock: socket.socket, n: int) -> list[dict]:
    buf = b""
    while buf.count(b"\n") < n:
        chunk = sock.recv(65536)
        assert chunk, f"connection closed after {buf.count(NL)} of {n} replies"
        buf += chunk
    return [json.loads(x) for x in buf.split(b"\n")[:n]]


def test_one_reply_per_line_in_order(server):
    assert oct(os.stat(server.path).st_mode & 0o777) == "0o660"
    with socket.socket(socket.AF_UNIX) as s:
        s.connect(str(server.path))
        s.sendall(b'{"cmd":"status","id":1}\n{"cmd":"dance","id":2}\r\nnope\n{"cmd":"stop","id":3}\n'
                  b'{"cmd":"reset","id":4}\n\n')
        r = _lines(s, 6)
    assert [x["id"] for x in r[:2]] == [1, 2]
    assert r[0]["ok"] and r[0]["result"] == {"echo": "status", "nan": None} and r[0]["state"] == "IDLE"
    assert r[1]["error"]["code"] == "unknown_command"
    assert r[2]["error"]["code"] == "bad_request"
    assert r[3]["error"] == {"code": "wrong_state", "message": "not now"}
    assert r[4]["error"]["code"] == "failed" and "handler bug" in r[4]["error"]["message"]
    assert r[5]["error"]["code"] == "bad_request"


def test_over_long_line_gets_one_reply_and_the_connection_goes_on(server):
    with socket.socket(socket.AF_UNIX) as s:
        s.connect(str(server.path))
        s.sendall(b"x" * (3 * MAX_REQUEST_BYTES))  # no newline yet: the server must not buffer it all
        s.sendall(b"y" * 1000 + b'\n{"cmd":"ping"}\n')
        r = _lines(s, 2)
    assert r[0]["error"]["code"] == "too_long"
    assert r[1]["ok"] and r[1]["result"]["echo"] == "ping"


def test_second_server_on_the_same_path_is_refused_and_stale_socket_replaced(server, tmp_path):
    other = ControlServer(server.path, lambda r: {}, lambda: "IDLE", PeerPolicy(None))
    with pytest.raises(SocketInUse):
        other.start()
    stale = tmp_path / "stale.sock"
    s = socket.socket(socket.AF_UNIX)
    s.bind(str(stale))
    s.close()  # a socket file nobody listens on, as a killed daemon leaves it
    again = ControlServer(stale, lambda r: {"fine": True}, lambda: "IDLE", PeerPolicy(None))
    again.start()
    try:
        with socket.socket(socket.AF_UNIX) as c:
            c.connect(str(stale))
            c.sendall(b'{"cmd":"ping"}\n')
            assert _lines(c, 1)[0]["result"] == {"fine": True}
    finally:
        again.stop()


def _connect_as(uid: int, path: str) -> dict:
    """Fork a child that drops to ``uid`` and sends one request; return what it received."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # child
        try:
            os.close(r)
            os.setgroups([])
            os.setgid(uid)
            os.setuid(uid)
            with socket.socket(socket.AF_UNIX) as s:
                s.settimeout(10)
                s.connect(path)
                try:
                    s.sendall(b'{"cmd":"status"}\n')
                except OSError:
                    pass
                data = read_line(s)
            os.write(w, data or b'{"closed": true}\n')
        except BaseException as exc:  # report anything to the parent
            os.write(w, json.dumps({"child_error": repr(exc)}).encode() + b"\n")
        finally:
            os._exit(0)
    os.close(w)
    with os.fdopen(r, "rb") as f:
        out = f.read()
    os.waitpid(pid, 0)
    return json.loads(out.splitlines()[0])


def test_peer_credentials_not_file_mode_decide():
    if os.getuid() != 0:
        pytest.skip("needs root to switch to another uid")
    seen: list[Request] = []
    # pytest's tmp_path is private to root; the other uid must be able to reach the socket file
    with tempfile.TemporaryDirectory(prefix="flgd-peer-", dir="/tmp") as d:
        os.chmod(d, 0o755)
        srv = ControlServer(Path(d) / "ctl.sock", lambda r: seen.append(r) or {"served": True}, lambda: "IDLE",
                            PeerPolicy(None))
        srv.start()
        try:
            os.chmod(srv.path, 0o666)  # file permissions now let anyone connect: SO_PEERCRED must refuse
            reply = _connect_as(65534, str(srv.path))
            assert reply.get("error", {}).get("code") == "forbidden", reply
            assert "uid 65534" in reply["error"]["message"]
            assert seen == []  # the request never reached the handler
            assert srv.refused_peers == 1
            assert _connect_as(0, str(srv.path))["result"] == {"served": True}  # root is allowed
        finally:
            srv.stop()


def test_peer_policy_group_membership(tmp_path):
    import grp
    policy = PeerPolicy(grp.getgrgid(0).gr_name)
    assert policy.allows(0, 0) and policy.allows(12345, 0)
    assert not PeerPolicy(None).allows(65534, 65534)
    with pytest.raises(ValueError, match="does not exist"):
        PeerPolicy("no-such-group-flgd")


def test_many_clients_at_once(server):
    """As many clients of one account as it may hold connections (more are refused as busy: the limits'
    own tests) are all served at once.  With more, whether the last ones found a slot depended on how fast
    the server closed the first ones, i.e. on the machine's load."""
    from flgd.daemon.server import MAX_CONNECTIONS_PER_UID

    errors: list[str] = []

    def client(i: int) -> None:
        try:
            with socket.socket(socket.AF_UNIX) as s:
                s.connect(str(server.path))
                s.sendall(json.dumps({"cmd": "ping", "id": i}).encode() + b"\n")
                r = _lines(s, 1)[0]
                if r["id"] != i or not r["ok"]:
                    errors.append(str(r))
        except Exception as exc:
            errors.append(repr(exc))

    threads = [threading.Thread(target=client, args=(i,)) for i in range(MAX_CONNECTIONS_PER_UID)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
