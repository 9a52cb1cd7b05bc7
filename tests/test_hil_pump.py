"""A child's pipe read to its end (hil_server.pump): bounded lines, per-destination caps, nothing lost silently."""

from __future__ import annotations

import io

from hil_server.pump import MAX_LINE_BYTES, Sink, pump


def test_a_line_without_end_is_passed_on_in_bounded_pieces_and_every_byte_arrives():
    # a program printing without a newline grew one line without end in the reader's memory
    data = b"x" * (5 * MAX_LINE_BYTES + 7) + b"\nlast\n"
    got: list[bytes] = []
    pump(io.BytesIO(data), [Sink(got.append)])
    assert b"".join(got) == data
    assert max(len(g) for g in got) <= MAX_LINE_BYTES and len(got) == 7


def test_a_cap_passes_whole_lines_then_says_how_many_bytes_it_did_not():
    data = b"".join(b"%03d\n" % i for i in range(100))  # 100 lines of 4 bytes
    capped: list[bytes] = []
    tail: list[bytes] = []
    pump(io.BytesIO(data), [Sink(capped.append, cap=42, over=lambda n: b"(%d not kept)\n" % n)], on_line=tail.append)
    assert b"".join(capped[:-1]) == data[:40] and capped[-1] == b"(360 not kept)\n"
    assert b"".join(tail) == data  # the tail sees every line whatever the caps


def test_a_sink_that_fails_ends_alone_and_the_pipe_is_still_read_to_its_end():
    data = b"a\nb\nc\n"
    stream = io.BytesIO(data)

    def broken(_: bytes) -> None:
        raise OSError(28, "No space left on device")

    got: list[bytes] = []
    pump(stream, [Sink(broken, cap=1, over=lambda n: b"never"), Sink(got.append)])
    assert b"".join(got) == data and stream.closed
