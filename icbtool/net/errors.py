"""The protocol's error codes, its exception and its base64: the bottom of :mod:`icbtool.net`.

:mod:`~icbtool.net.protocol` (framing, schema), :mod:`~icbtool.net.crypto` (handshake, sealing)
and :mod:`~icbtool.net.codec` (GI maps) all raise :class:`ProtocolError`; they import it from
here, so none of them imports another to report an error (docs/protocol.md, section Errors).
"""

from __future__ import annotations

import base64
import binascii

#: Largest integer magnitude a field may hold (JavaScript's Number.MAX_SAFE_INTEGER).
MAX_SAFE_INTEGER = 2**53 - 1

#: Every error code a :class:`ProtocolError` (and an ``error`` message) can carry.
ERROR_CODES: dict[str, str] = {
    "malformed": "the frame cannot be parsed: too short, header length beyond the data, bad "
    "UTF-8 or JSON, duplicate keys, a header that is not an object, no v/kind",
    "version": "the header's v is not the receiver's PROTOCOL_VERSION",
    "unknown_kind": "the header's kind is not one of the message kinds",
    "too_large": "the message or its header is over the receiver's size limit",
    "bad_field": "a field is missing, has the wrong type or an invalid value (the message names "
    "the kind and the field); also a payload where the kind has none, or one that does not match "
    "its description (sizes, hash); a request over a documented limit (section Limits); a "
    "gi_request whose id is already pending on the connection",
    "auth": "the client's authentication failed (wrong token) or a message came before it",
    "crypto": "a sealed message failed to decrypt or authenticate (tampered header or payload, "
    "wrong key), or a message was sealed when it must not be (or not when it must)",
    "replay": "a sealed message's counter is not above the last one accepted in its direction",
    "busy": "the server is at capacity (too many queued requests, of this client or of all); "
    "try again later (section For client authors)",
    "internal": "the peer failed while handling a valid message (e.g. a render worker was lost "
    "twice); the request may be sent again",
    "not_found": "the message names something that does not exist (an LPM level range with no "
    "level offered, a client model or model chunk not on offer)",
}


def safe_ref(ref: object) -> int | None:
    """``ref`` when it may travel as an ``error.ref`` (an integer in [0, 2^53 - 1]), else None.

    A request whose id is out of range is answered with ``ref: null``: the reply itself must
    always be valid (docs/protocol.md, section Errors).
    """
    if isinstance(ref, int) and not isinstance(ref, bool) and 0 <= ref <= MAX_SAFE_INTEGER:
        return ref
    return None


class ProtocolError(ValueError):
    """A message broke the protocol, or the peer reported an error.

    Attributes:
        code: one of :data:`ERROR_CODES`.
        message: what was wrong, naming the kind and field where there is one.
        ref: the ``id`` of the request it concerns (``gi_request.id``), or None; an id out of
            the protocol's integer range is dropped (None), see :func:`safe_ref`.
    """

    def __init__(self, code: str, message: str, ref: int | None = None) -> None:
        if code not in ERROR_CODES:
            raise ValueError(
                f"ProtocolError code must be one of {sorted(ERROR_CODES)}, got {code!r}"
            )
        super().__init__(f"[{code}] {message}")
        self.code = code
        self.message = message
        self.ref = safe_ref(ref)


def b64(data: bytes) -> str:
    """Standard base64 with padding (RFC 4648 section 4), as the protocol's base64 fields use."""
    return base64.b64encode(data).decode("ascii")


def unb64(text: str, what: str = "value") -> bytes:
    """Inverse of :func:`b64`.

    Raises:
        ProtocolError: ``"bad_field"`` naming ``what`` when ``text`` is not valid base64.
    """
    try:
        return base64.b64decode(text.encode("ascii"), validate=True)
    except (binascii.Error, UnicodeEncodeError, ValueError, AttributeError):
        raise ProtocolError("bad_field", f"{what}: is not valid base64") from None


__all__ = ["ERROR_CODES", "MAX_SAFE_INTEGER", "ProtocolError", "b64", "safe_ref", "unb64"]
