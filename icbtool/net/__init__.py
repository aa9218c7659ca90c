"""The networked ICB system's wire layer: message framing, session crypto, GI/depth codecs.

* :mod:`icbtool.net.errors`: the error codes, :class:`ProtocolError` and base64, which the
  protocol, crypto and codec modules share (none of them imports another to raise one).
* :mod:`icbtool.net.protocol`: one WebSocket binary message = ``u32 header length | JSON header
  | payload``; the message kinds and their fields (docs/protocol.md).
* :mod:`icbtool.net.crypto`: X25519 + HKDF-SHA256 session keys, token authentication by HMAC,
  AES-256-GCM sealing of every payload after the handshake (needs the ``net`` extra).
* :mod:`icbtool.net.codec`: HDR codecs for GI maps and depth (needs the ``net`` extra).

* :mod:`icbtool.net.server`: :class:`Server` (``icbtool serve``), the cloud behind a WebSocket;
* :mod:`icbtool.net.client`: :class:`NetworkSource`, a GI source over a WebSocket;
  :mod:`icbtool.net.run`: :func:`run_client` (``icbtool client``); :mod:`icbtool.net.shaper`:
  :class:`ShaperConfig` (emulated latency and bandwidth).

Only the protocol is imported here; crypto and codec load their optional dependencies on use, and
the server/client names load their modules on first access.
"""

from typing import Any

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

_LAZY = {
    "Server": "icbtool.net.server",
    "ServerConfig": "icbtool.net.server",
    "NetworkSource": "icbtool.net.client",
    "NetClientConfig": "icbtool.net.client",
    "NetError": "icbtool.net.client",
    "ShaperConfig": "icbtool.net.shaper",
    "run_client": "icbtool.net.run",
    "NetRunReport": "icbtool.net.run",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'icbtool.net' has no attribute {name!r}")


__all__ = [
    *_LAZY,
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
