"""LiveSource against the RAW_IMU sender over real sockets on 127.0.0.1 (no other network).

Every test is bounded: the LiveSource has a timeout, a watchdog closes it, sender threads get a stop event
and are joined with a timeout.
"""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest
from netutil import Sender, free_port

from onlinecal.io.base import ImuData, LogError
from onlinecal.io.live import LiveSource
from onlinecal.sim.sensors import simulate
from onlinecal.testing.sender import fault_schedule, send_session

G0 = 9.80665
WATCHDOG_S = 15.0  # no single stream in this file may take longer


@pytest.fixture(scope="module")
def session() -> ImuData:
    """20 s of the paper's session at 100 Hz (IMU) / 50 Hz (mag)."""
    return simulate("paper", 3, duration=20.0).data


def consume(src: LiveSource) -> tuple[ImuData, list[ImuData]]:
    """All blocks of ``src`` (closed by a watchdog after WATCHDOG_S s), joined."""
    dog = threading.Timer(WATCHDOG_S, src.close)
    dog.start()
    try:
        blocks = list(src.blocks())
    finally:
        dog.cancel()
    assert src.stats["stop_reason"] != "closed", "watchdog fired: the stream did not end by itself"
    return ImuData.concat(blocks, src.url), blocks


def expected_mag(data: ImuData) -> tuple[np.ndarray, np.ndarray]:
    """What a receiver can know of the mag: mgauss counts held at each IMU tick, changes only, no zeros."""
    q = np.rint(data.mag / 1e-3)
    j = np.searchsorted(data.t_mag, data.t_imu, side="right") - 1
    held = np.where((j >= 0)[:, None], q[np.maximum(j, 0)], 0.0)
    change = np.ones(len(held), bool)
    change[1:] = np.any(held[1:] != held[:-1], axis=1)
    keep = change & np.any(held != 0, axis=1)
    return data.t_imu[keep], held[keep] * 1e-3


def match_sent(out: ImuData, data: ImuData) -> np.ndarray:
    """Index of each received IMU sample in the sent session (by time, to the µs)."""
    i = np.searchsorted(data.t_imu, out.t_imu - 1e-6)
    i = np.minimum(i, data.n_imu - 1)
    assert np.all(np.abs(data.t_imu[i] - out.t_imu) <= 1e-6), "a received time was never sent"
    return i


def assert_values(out: ImuData, data: ImuData, i: np.ndarray) -> None:
    """Received = sent within half an int16 count of RAW_IMU's units."""
    assert np.all(np.abs(out.gyro - data.gyro[i]) <= 0.5e-3 + 1e-12)
    assert np.all(np.abs(out.acc - data.acc[i]) <= 0.5 * G0 * 1e-3 + 1e-12)
    assert np.all(np.abs(out.temp - data.temp[i]) <= 0.005 + 1e-9)


@pytest.mark.slow
def test_clean_stream_equals_sent_and_rate_request_acknowledged(session: ImuData) -> None:
    port = free_port()
    src = LiveSource(f"udpin:127.0.0.1:{port}", rate_hz=100, reconnect_s=2.0, timeout_s=0.7)
    snd = Sender(lambda stop: send_session(session, f"udpout:127.0.0.1:{port}", rate_scale=0.05,
                                           stop_event=stop))
    try:
        out, blocks = consume(src)
    finally:
        snd.finish()
    assert src.stats["stop_reason"] == "timeout"
    assert out.n_imu == session.n_imu
    assert np.allclose(out.t_imu, session.t_imu, atol=1e-6, rtol=0)
    assert_values(out, session, np.arange(session.n_imu))
    tm, mag = expected_mag(session)
    assert out.n_mag == tm.size
    assert np.allclose(out.t_mag, tm, atol=1e-6, rtol=0)
    assert np.allclose(out.mag, mag, atol=1e-12, rtol=0)
    # Blocks of about block_s (0.25 s at 100 Hz: some 25 samples), in order.
    sizes = [b.n_imu for b in blocks[:-1]]
    assert 20 <= np.median(sizes) <= 30
    assert all(a.t_imu[-1] < b.t_imu[0] for a, b in zip(blocks, blocks[1:], strict=False) if b.n_imu)
    # The rate request went out after the vehicle's heartbeat and was acknowledged (ACCEPTED = 0).
    assert src.stats["interval_requests"] >= 1
    assert src.stats["ack"] >= 1 and src.stats["ack_result"] == 0
    assert snd.result["commands"] >= 1 and snd.result["interval_us"] == 10_000
    for k in ("duplicates", "reordered", "dropped_late", "reconnects"):
        assert src.stats[k] == 0, k


@pytest.mark.slow
def test_lossy_link_drop_reorder_duplicate(session: ImuData) -> None:
    port = free_port()
    src = LiveSource(f"udpin:127.0.0.1:{port}", reconnect_s=2.0, timeout_s=0.7)
    snd = Sender(lambda stop: send_session(session, f"udpout:127.0.0.1:{port}", rate_scale=0.05, drop=0.10,
                                           reorder=0.05, duplicate=0.05, seed=7, stop_event=stop))
    try:
        out, _ = consume(src)
    finally:
        snd.finish()
    assert np.all(np.diff(out.t_imu) > 0), "output not strictly increasing (or duplicated)"
    assert np.all(np.diff(out.t_mag) > 0)
    assert 0.85 <= out.n_imu / session.n_imu <= 0.95
    # What arrived is exactly what was sent, and every packet that went out (once) is there.
    assert_values(out, session, match_sent(out, session))
    assert out.n_imu == session.n_imu - snd.result["dropped"]
    st = src.stats
    assert st["reordered"] > 0 and st["duplicates"] > 0
    assert st["duplicates"] == snd.result["duplicated"]
    assert st["dropped_late"] == 0  # reordering by at most 3 packets fits in the 32-packet window
    assert any("duplicate" in w for w in out.warnings)
    # Loss counted from the time line: every sent sample missing between the first and last received.
    i = match_sent(out, session)
    assert st["lost"] == (i[-1] - i[0] + 1) - out.n_imu
    # Every mag sample used has its true time: a change first seen right after a lost packet happened
    # somewhere in the gap, so it is not used (mag_uncertain) rather than stamped late.
    tm, mag = expected_mag(session)
    j = np.searchsorted(tm, out.t_mag - 1e-7)
    assert np.all(np.abs(tm[np.minimum(j, tm.size - 1)] - out.t_mag) <= 1e-6), "a mag sample is mistimed"
    assert np.allclose(out.mag, mag[j], atol=1e-12, rtol=0)
    assert st["mag_uncertain"] > 0 and out.n_mag + st["mag_uncertain"] <= tm.size


def test_resume_from_position_continues_the_time_line(session: ImuData) -> None:
    """A second source resumed from the first one's position emits only later samples, keeps the clock
    start (duration_s counts from the first source's first sample) and the held mag triple."""
    port1, port2 = free_port(), free_port()
    a_part, b_part = session.slice_imu(0, 400), session.slice_imu(300, 900)  # b repeats 100 samples
    src = LiveSource(f"udpin:127.0.0.1:{port1}", timeout_s=0.7)
    snd = Sender(lambda stop: send_session(a_part, f"udpout:127.0.0.1:{port1}", rate_scale=0.05,
                                           stop_event=stop))
    try:
        out_a, _ = consume(src)
    finally:
        snd.finish()
        src.close()
    pos = src.position()
    assert pos is not None and pos["last_us"] == round(a_part.t_imu[-1] * 1e6)
    t0 = float(session.t_imu[0])
    src = LiveSource(f"udpin:127.0.0.1:{port2}", timeout_s=0.7, duration_s=7.0)
    src.resume_from(pos)
    snd = Sender(lambda stop: send_session(b_part, f"udpout:127.0.0.1:{port2}", rate_scale=0.05,
                                           stop_event=stop))
    try:
        out_b, _ = consume(src)
    finally:
        snd.finish()
        src.close()
    # Only the samples after the position, up to 7 s after the *first* source's first sample.
    want = session.t_imu[(session.t_imu > a_part.t_imu[-1]) & (session.t_imu <= t0 + 7.0 + 1e-9)]
    assert np.allclose(out_b.t_imu, want, atol=1e-6, rtol=0)
    assert src.stats["stop_reason"] == "duration" and src.stats["lost"] == 0
    # The held mag carried over: the first mag sample of b is a real change, at its true time.
    tm, _ = expected_mag(session)
    assert out_b.n_mag and out_b.t_mag[0] == pytest.approx(tm[tm > a_part.t_imu[-1]][0], abs=1e-6)
    with LiveSource(f"udpin:127.0.0.1:{free_port()}") as bad, pytest.raises(ValueError, match="position"):
        bad.resume_from({"last_us": 1})


@pytest.mark.slow
def test_udp_reconnect_after_silence(session: ImuData) -> None:
    port = free_port()
    url = f"udpout:127.0.0.1:{port}"
    half = session.n_imu // 2
    first, second = session.slice_imu(0, half), session.slice_imu(half, session.n_imu)
    t_pause = float(first.t_imu[-1])

    def two_sessions(stop: threading.Event) -> list[dict]:
        a = send_session(first, url, rate_scale=0.05, stop_event=stop)
        stop.wait(1.5)  # longer than reconnect_s: the receiver gives the link up and re-opens it
        b = send_session(second, url, rate_scale=0.05, stop_event=stop)  # a new socket, new source port
        return [a, b]

    src = LiveSource(f"udpin:127.0.0.1:{port}", reconnect_s=0.4, timeout_s=5.0,
                     duration_s=float(session.t_imu[-1] - session.t_imu[0]))
    snd = Sender(two_sessions)
    try:
        out, _ = consume(src)
    finally:
        snd.finish()
    st = src.stats
    assert st["stop_reason"] == "duration"
    assert st["reconnects"] >= 1
    after = out.t_imu > t_pause
    assert after.sum() == second.n_imu  # all of the second session arrived after the pause
    assert np.all(np.diff(out.t_imu) > 0)
    assert st["interval_requests"] >= 2 and st["ack"] >= 2  # the request is sent again after re-opening
    assert any("re-opened" in w for w in out.warnings)


@pytest.mark.slow
def test_tcp_reconnect_after_server_restart(session: ImuData) -> None:
    port = free_port(socket.SOCK_STREAM)
    url = f"tcpin:127.0.0.1:{port}"
    half = session.n_imu // 2
    first, second = session.slice_imu(0, half), session.slice_imu(half, session.n_imu)

    def two_servers(stop: threading.Event) -> list[dict]:
        a = send_session(first, url, rate_scale=0.05, stop_event=stop, wait_peer_s=5.0)
        stop.wait(0.8)  # the vehicle is gone: the client sees EOF, then refused connections
        b = send_session(second, url, rate_scale=0.05, stop_event=stop, wait_peer_s=5.0)
        return [a, b]

    snd = Sender(two_servers)
    try:
        src = None
        deadline = time.monotonic() + 3.0
        while src is None:  # the server thread may not be listening yet
            try:
                src = LiveSource(f"tcp:127.0.0.1:{port}", reconnect_s=0.4, timeout_s=5.0,
                                 duration_s=float(session.t_imu[-1] - session.t_imu[0]))
            except LogError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)
        out, _ = consume(src)
    finally:
        snd.finish()
    assert src.stats["stop_reason"] == "duration"
    assert src.stats["reconnects"] >= 1
    assert np.sum(out.t_imu > first.t_imu[-1]) == second.n_imu
    assert np.all(np.diff(out.t_imu) > 0)
    assert_values(out, session, match_sent(out, session))
    assert all(r["peer"] for r in snd.result)


def test_udpout_receiver_reaches_udpin_vehicle(session: ImuData) -> None:
    """Roles swapped: the vehicle listens, the receiver sends first (its heartbeat tells the address)."""
    port = free_port()
    data = session.slice_imu(0, 500)
    snd = Sender(lambda stop: send_session(data, f"udpin:127.0.0.1:{port}", rate_scale=0.05, stop_event=stop,
                                           wait_peer_s=5.0))
    time.sleep(0.1)  # let the vehicle bind (a missed heartbeat would only cost 0.25 s)
    src = LiveSource(f"udpout:127.0.0.1:{port}", timeout_s=0.7)
    try:
        out, _ = consume(src)
    finally:
        snd.finish()
    assert snd.result["peer"]
    assert out.n_imu == data.n_imu
    assert src.stats["ack"] >= 1


def test_vehicle_clock_restart_is_a_new_segment(session: ImuData) -> None:
    """A reboot mid-stream: time_usec starts again near 0. The time line continues instead of every later
    sample being dropped as late, and (issue 16.2) not as a splice: a 2 s segment gap and a boundary on the
    block that holds it, so the filter restarts the attitude there."""
    port = free_port()
    url = f"udpout:127.0.0.1:{port}"
    first, again = session.slice_imu(0, 600), session.slice_imu(0, 400)  # the second boot's clock restarts

    def reboot(stop: threading.Event) -> list[dict]:
        return [send_session(first, url, rate_scale=0.05, stop_event=stop),
                send_session(again, url, rate_scale=0.05, stop_event=stop)]

    src = LiveSource(f"udpin:127.0.0.1:{port}", reconnect_s=2.0, timeout_s=0.7)
    snd = Sender(reboot)
    try:
        out, _ = consume(src)
    finally:
        snd.finish()
    assert src.stats["clock_resets"] == 1
    assert out.n_imu == first.n_imu + again.n_imu
    assert np.all(np.diff(out.t_imu) > 0)
    dt = np.diff(out.t_imu)
    k = first.n_imu - 1
    assert np.allclose(np.delete(dt, k), 0.01, atol=1e-6) and dt[k] == pytest.approx(2.0, abs=1e-6)
    assert [b["cause"] for b in out.boundaries] == ["clock restart"]
    assert out.t_imu[k] < out.boundaries[0]["t"] < out.t_imu[k + 1]
    assert out.boundaries[0]["before_s"] == pytest.approx(first.t_imu[-1], abs=1e-6)
    assert out.boundaries[0]["after_s"] == pytest.approx(again.t_imu[0], abs=1e-6)
    assert src.boundaries == out.boundaries
    assert np.allclose(out.gyro[first.n_imu:], again.gyro, atol=0.5e-3 + 1e-12)
    assert any("clock went back" in w and "new segment" in w for w in out.warnings)


def test_close_from_another_thread_ends_stream_and_hands_on_what_is_held(session: ImuData) -> None:
    port = free_port()
    data = session.slice_imu(0, 200)
    # A window and blocks larger than the whole stream: nothing is yielded until close().
    src = LiveSource(f"udpin:127.0.0.1:{port}", timeout_s=10.0, block_s=100.0, reorder_window=1000)
    snd = Sender(lambda stop: send_session(data, f"udpout:127.0.0.1:{port}", stop_event=stop))
    threading.Timer(0.8, src.close).start()
    t0 = time.monotonic()
    try:
        blocks = list(src.blocks())
    finally:
        snd.finish()
    assert time.monotonic() - t0 < 3.0
    assert src.stats["stop_reason"] == "closed"
    assert len(blocks) == 1 and blocks[0].n_imu == data.n_imu


def test_nothing_received_is_a_log_error() -> None:
    src = LiveSource(f"udpin:127.0.0.1:{free_port()}", timeout_s=0.3)
    with pytest.raises(LogError, match="nothing received"):
        list(src.blocks())


@pytest.mark.parametrize("url, why", [
    ("udpin:127.0.0.1", "host:port"),
    ("udpin:127.0.0.1:99999", "port"),
    ("udpin:127.0.0.1:http", "invalid literal"),
    ("tcp:127.0.0.1:{tcp_port}", "refused"),
    ("/dev/no-such-tty,115200", "no such device"),
    ("session.tlog", "log file"),
])
def test_bad_url_is_a_log_error(url: str, why: str) -> None:
    url = url.format(tcp_port=free_port(socket.SOCK_STREAM))
    t0 = time.monotonic()
    with pytest.raises(LogError) as ei:
        LiveSource(url)
    assert time.monotonic() - t0 < 2.0
    msg = str(ei.value)
    assert msg.startswith(f"{url}: cannot open connection: ")
    assert why.lower() in msg.lower()
    assert "\n" not in msg


def test_fault_schedule_counts() -> None:
    order, counts = fault_schedule(10_000, 0.1, 0.05, 0.05, np.random.default_rng(0))
    ks = [k for k, _ in order]
    assert len(set(ks)) == 10_000 - counts["dropped"]
    assert sum(c for _, c in order) == len(ks) + counts["duplicated"]
    assert abs(counts["dropped"] - 1000) < 150
    # Reordered packets go at most 3 places late.
    pos = {k: p for p, k in enumerate(ks)}
    assert max(pos[k] - r for r, k in enumerate(sorted(ks))) <= 3
    with pytest.raises(ValueError):
        fault_schedule(10, 1.5, 0, 0, np.random.default_rng(0))
