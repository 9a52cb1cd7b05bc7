"""The HIL server when a flight process ends: its last messages are taken before its exit is judged, and a pair
whose frames never reached it is the next process's, not its crash (QA 64a M1, review of stop 64)."""

from __future__ import annotations

import socket
import time
from types import SimpleNamespace

from hil_server.supervisor import PairState, Reader, Supervisor
from protocol.links import LOCAL_CONFIG, PTY_CONFIG, StreamLink
from protocol.messages import Error


def test_a_dead_processs_last_messages_are_taken_before_its_exit_is_judged():
    """Taken after the restart, they were a dead incarnation's and dropped: a pair answered in full whose Telemetry
    was still in the link was sent to the next process again. Here the link's reader thread is late to parse the
    last message (a loaded host): it is still taken, and the ground's events stay queued in their order."""
    a_sock, b_sock = socket.socketpair()
    server = StreamLink(a_sock, config=LOCAL_CONFIG, name="server-side")
    slow = {"on": False}
    read = server._read

    def late_read(timeout):
        data = read(timeout)
        if data and slow["on"]:
            time.sleep(0.4)  # read, not yet parsed
        return data

    server._read = late_read  # type: ignore[method-assign]
    time.sleep(0.2)  # its reader thread is in the patched read from now on
    flight = StreamLink(b_sock, config=LOCAL_CONFIG, name="flight-side")
    try:
        assert server.wait_established(5) and flight.wait_established(5)
        sup = Supervisor(None, SimpleNamespace(deadline_s=2.0), None, log=lambda s: None)
        sup.flight = SimpleNamespace(generation=1, link=server, says_eof=True)  # type: ignore[assignment]
        sup.flight_reader = Reader(server, "flight", sup.events, 1)
        sup.flight_reader.start()
        sup.events.put(("ground", 0, "a ground message", 1))
        taken: list[str] = []
        sup._on_flight = lambda gen, msg: taken.append(msg.text)  # type: ignore[method-assign]
        flight.send(Error(code="m", text="Result"))
        time.sleep(0.5)
        slow["on"] = True
        flight.send(Error(code="m", text="Telemetry"))  # its last words, then it ends
        time.sleep(0.05)
        b_sock.shutdown(socket.SHUT_RDWR)
        time.sleep(0.05)
        sup._take_last_words()
        assert taken == ["Result", "Telemetry"]
        assert list(sup.events.queue) == [("ground", 0, "a ground message", 1)]
    finally:
        server.close()
        flight.close()


def test_a_pair_none_of_whose_frames_reached_the_dead_process_is_not_its_crash():
    """Frames forwarded as a process died (the pair after its last answer) were failed as "died while processing";
    a pair it had any frame of is its crash, and a second death on the same pair is one too (no crash loop)."""
    outcomes = {5: "pending", 6: "pending", 7: "delivered", 8: "pending"}
    sup = Supervisor(None, SimpleNamespace(deadline_s=2.0), None, log=lambda s: None)
    link = SimpleNamespace(outcome=outcomes.get)
    sup.flight = SimpleNamespace(generation=3, link=link)  # type: ignore[assignment]
    never = PairState("a", sent_to=3, frame_mids={0: 5, 1: 6})
    half = PairState("b", sent_to=3, frame_mids={0: 7, 1: 8})
    earlier = PairState("c", sent_to=2, frame_mids={0: 5, 1: 6})  # sent to another incarnation: not known here
    assert not sup._reached_flight(never)
    assert sup._reached_flight(half) and sup._reached_flight(earlier)


def test_a_new_ground_session_is_passed_on_to_the_flight_process():
    """Under ``run`` the flight process was not told of a new ground session, so it held the old session's half
    pair and 8 pairs later said it dropped it, about a pair the server had closed (QA 65f L1). The server now passes
    each new ground's Hello on, and a repeated Hello of the same session is not."""
    from protocol.messages import Hello

    sent: list = []
    sup = Supervisor(None, SimpleNamespace(deadline_s=2.0), None, log=lambda s: None)
    link = SimpleNamespace(send=lambda m, epoch=None: sent.append(m))
    sup.flight = SimpleNamespace(generation=1, link=link, epoch=None)  # type: ignore[assignment]
    sup._new_ground_session(Hello(role="ground", session=11), epoch=1)
    sup._new_ground_session(Hello(role="ground", session=11), epoch=1)  # the same ground again
    sup._new_ground_session(Hello(role="ground", session=12), epoch=2)
    assert [(type(m).__name__, m.session) for m in sent] == [("Hello", 11), ("Hello", 12)]
    assert sup.ground_gen == 2


def test_the_hil_servers_local_link_keeps_a_rule_7_peers_session_through_silence():
    """docs/protocol.md section 2: a HELLO after 1 s without sending (rule 6), and a peer gives its session up after
    `peer_timeout` without a frame (rule 7). The server's side of its local link sent one every 5 s, so a
    `--flight-cmd` program kept to both lost its session in every 4 s the server had nothing to say (QA of stop
    79). Here the program's timeout is 2 s: 3 s of silence on both sides must not cost it its session."""
    from protocol.arq import ArqConfig

    a_sock, b_sock = socket.socketpair()
    server = StreamLink(a_sock, config=PTY_CONFIG, name="server-side")  # the HIL server's side of their pty
    program = StreamLink(b_sock, config=ArqConfig(peer_timeout=2.0, keepalive=5.0), name="their-program")
    try:
        assert server.wait_established(5) and program.wait_established(5)
        epoch = program.epoch
        time.sleep(3.0)
        assert program.established and program.epoch == epoch, program.last_error
    finally:
        program.close()
        server.close()
