"""The networked ICB system's wire layer: message framing, session crypto, GI/depth codecs.

* :mod:`icbtool.net.protocol`: one WebSocket binary message = ``u32 header length | JSON header
  | payload``; the message kinds and their fields (docs/protocol.md).
* :mod:`icbtool.net.crypto`: X25519 + HKDF-SHA256 session keys, token authentication by HMAC,
  AES-256-GCM sealing of every payload after the handshake (needs the ``net`` extra).
* :mod:`icbtool.net.codec`: HDR codecs for GI maps and depth (needs the ``net`` extra).

Only the protocol is imported here; crypto and codec load their optional dependencies on use.
"""

from icbtool.net.protocol import (
    DEFAULT_MAX_MESSAGE,
    KINDS,
    MAX_HEADER,
    PROTOCOL_VERSION,
    Message,
    ProtocolError,
    camera_from_json,
    camera_to_json,
    decode,
    encode,
    error_message,
    request_from_json,
    request_to_json,
)

__all__ = [
    "DEFAULT_MAX_MESSAGE",
    "KINDS",
    "MAX_HEADER",
    "PROTOCOL_VERSION",
    "Message",
    "ProtocolError",
    "camera_from_json",
    "camera_to_json",
    "decode",
    "encode",
    "error_message",
    "request_from_json",
    "request_to_json",
]
