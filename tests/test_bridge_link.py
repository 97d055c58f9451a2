"""Link: reconnect with back-off over a real TCP socket (the peer goes away and comes back)."""
import socket
import threading
import time

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from mavlink_bridge.link import Link

MAV = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
HEARTBEAT = bytes(MAV.heartbeat_encode(2, 3, 0, 0, 4).pack(MAV))


def _serve_once(port=0, hold_s=0.3):
    """A TCP 'autopilot' that accepts one client, sends one HEARTBEAT and hangs up."""
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", port))
    srv.listen(1)

    def run():
        c, _ = srv.accept()
        c.sendall(HEARTBEAT)
        time.sleep(hold_s)
        c.close()
        srv.close()
    threading.Thread(target=run, daemon=True).start()
    return srv.getsockname()[1]


def _recv_types(link, seconds):
    out, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        m = link.recv(0.1)
        if m is not None:
            out.append(m.get_type())
    return out


def test_tcp_link_reconnects_after_peer_restart():
    port = _serve_once()
    link = Link(f"tcp:127.0.0.1:{port}", 0, 1, 197, reconnect_max_s=0.5)
    try:
        assert _recv_types(link, 1.0) == ["HEARTBEAT"]
        _recv_types(link, 1.0)  # peer gone: errors are absorbed, attempts back off
        assert link.conn is None and link.reconnects == 1
        assert not link.send(MAV.heartbeat_encode(18, 8, 0, 0, 4))  # link down: False, no exception
        _serve_once(port, hold_s=5.0)
        assert _recv_types(link, 1.5) == ["HEARTBEAT"]
        assert link.send(MAV.heartbeat_encode(18, 8, 0, 0, 4))
    finally:
        link.close()


def test_link_to_absent_peer_starts_and_retries():
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    link = Link(f"tcp:127.0.0.1:{port}", 0, 1, 197, reconnect_max_s=0.5)
    assert link.conn is None and link.recv(0.05) is None
    port2 = _serve_once(port)
    assert port2 == port and _recv_types(link, 2.0) == ["HEARTBEAT"]
    link.close()
