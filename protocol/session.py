"""Link sessions: who we are, who the peer is, and the handshake rules (docs/protocol.md, "Sessions").

Each link endpoint has a random, non-zero 32-bit session id. Every frame
carries ``src`` (the sender's session) and ``dst`` (the session the sender
believes it talks to; 0 while it knows none). HELLO frames carry the
handshake:

* A HELLO from a session we do not know replaces the peer: if we had one, it
  is *retired* (the peer restarted) and our sequence/reassembly state is reset
  by the caller. We answer with HELLO(dst = the new peer). (A byte-stream
  link's Arq first drops such a HELLO while the current peer still talks: a
  stranger's, docs/protocol.md rule 2.)
* A HELLO or any valid frame with ``dst`` = our id from the current peer
  establishes the session (the peer knows us). On establishing we send one
  HELLO so the other side establishes too (it stops there: an established
  side does not answer HELLOs addressed to it).
* A HELLO with ``dst`` = 0 or another id is answered with our HELLO (the peer
  does not know us yet, or knows an earlier incarnation of us).
* When we give up on a peer (silent or stalled for ``peer_timeout``, or it
  sent CLOSE), we take a new id of our own: whatever the peer still sends to
  the dead session is addressed to an id that is no longer ours. The peer id
  itself is not retired, so a peer that was only stalled can come back (it
  sees our new id, resets its side, and a new session starts).

Frames from retired sessions, or addressed to an id that is not ours, are
dropped and counted as ``old_session_frames``; frames from an unknown session
that are not HELLOs are ``foreign_frames``.
"""

from __future__ import annotations

import secrets
from collections import deque


def new_session_id() -> int:
    """A random non-zero u32 (genuinely random: a restarted peer must not reuse its old id)."""
    while True:
        sid = secrets.randbits(32)
        if sid:
            return sid


class SessionState:
    """The session half of a link endpoint; the caller owns timers and resets (see module doc)."""

    def __init__(self, session_id: int | None = None) -> None:
        if session_id is not None and not 0 < session_id < 2**32:
            raise ValueError(f"session id must be a non-zero u32, got {session_id}")
        self.local = session_id or new_session_id()
        self.peer = 0
        self.established = False
        self.epoch = 0  # sessions established so far (a new peer session increments it)
        self._retired: deque[int] = deque(maxlen=64)
        self._past_locals: deque[int] = deque(maxlen=64)  # this side's own ids before :meth:`lose` took new ones

    def retired(self, sid: int) -> bool:
        return sid in self._retired

    def was_local(self, sid: int) -> bool:
        """Whether ``sid`` is one of this side's own past session ids: a peer's frame addressed there is one it
        sent before it heard this side's loss, not a mistake of the peer's."""
        return sid in self._past_locals

    def classify(self, src: int, dst: int) -> str:
        """For a non-HELLO frame: ``ok``, ``old`` (a past session on either side) or ``foreign``."""
        if self.peer and src == self.peer:
            return "ok" if dst == self.local else "old"
        if src in self._retired or dst not in (0, self.local):
            return "old"
        return "foreign"

    def on_hello(self, src: int, dst: int) -> tuple[int | None, bool, bool]:
        """A HELLO arrived: returns ``(replaced_peer, reply, newly_established)``.

        ``replaced_peer`` is the retired peer id when a new peer session took over
        (the caller resets its state), else None. The caller must have dropped
        HELLOs from retired sessions (:meth:`retired`).
        """
        replaced = None
        if src != self.peer:
            if self.peer:
                replaced = self.peer
                self._retired.append(self.peer)
            self.peer = src
            self.established = False
        if dst == self.local:
            if not self.established:
                self.established = True
                self.epoch += 1
                return replaced, True, True
            return replaced, False, False
        return replaced, True, False

    def confirm(self) -> bool:
        """A valid non-HELLO frame from the peer addressed to us: establish if not yet. True if newly."""
        if self.established or not self.peer:
            return False
        self.established = True
        self.epoch += 1
        return True

    def lose(self) -> int:
        """Give up on the peer: forget it and take a new local id. Returns the peer id (0 if none)."""
        old = self.peer
        self._past_locals.append(self.local)
        self.local = new_session_id()
        self.peer = 0
        self.established = False
        return old


class SessionView:
    """The session properties an endpoint that keeps its :class:`SessionState` in ``sess`` exposes."""

    sess: SessionState

    @property
    def established(self) -> bool:
        return self.sess.established

    @property
    def epoch(self) -> int:
        return self.sess.epoch

    @property
    def session_id(self) -> int:
        return self.sess.local

    @property
    def peer_session(self) -> int:
        return self.sess.peer
