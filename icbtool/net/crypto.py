"""Session crypto: X25519 key exchange, token authentication by HMAC, AES-256-GCM channels.

The handshake (docs/protocol.md, section Handshake) in three plain messages::

    client -> hello   {pub: client X25519 public key, nonce: 32 random bytes, ...}
    server -> welcome {session, pub: server X25519 public key, nonce: 32 random bytes, ...}
    client -> auth    {mac: HMAC-SHA256(auth key, transcript)}

    transcript = "icbtool/net/v1" | 0x00 | client pub (32) | client nonce (32)
                 | server pub (32) | server nonce (32) | session (UTF-8)

The token itself never travels. Both sides derive three keys with HKDF-SHA256 from the X25519
shared secret *and the token* (ikm = shared secret | token; salt = SHA-256(transcript); info =
"icbtool/net/v1 c2s", "icbtool/net/v1 s2c" and "icbtool/net/v1 auth"): one AES-256-GCM key per
direction and the key of the mac. The server checks the mac in constant time
(:func:`hmac.compare_digest`) and answers a wrong one with an ``auth`` error. So a peer that does
not hold the token cannot read or forge anything, even one that runs the key exchange itself, and
since the mac's key needs the shared secret, a recorded handshake does not let an eavesdropper
test token guesses offline (an active man in the middle, who runs the key exchange with the
client itself, still can: TLS closes that; docs/protocol.md section Threat model). Keys are
ephemeral: one pair per connection.

Every message after the handshake is sealed by a :class:`Channel`: the GCM nonce is the 4-byte
direction id (``00 00 00 01`` client to server, ``00 00 00 02`` server to client) followed by the
sender's 8-byte big-endian message counter (0, 1, 2, ...); the receiver accepts only counters
above the last one it accepted, so a replayed or reordered message is rejected.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import struct
import threading
from collections.abc import Sequence
from typing import Any

from icbtool.net.errors import ProtocolError, b64, unb64
from icbtool.optional import require

#: Prefix of the transcript and of the HKDF info strings.
LABEL = b"icbtool/net/v1"
#: Direction ids: the first 4 bytes of every GCM nonce.
CLIENT_TO_SERVER = b"\x00\x00\x00\x01"
SERVER_TO_CLIENT = b"\x00\x00\x00\x02"
#: Bytes of a public key, a handshake nonce, a mac, a GCM key and a GCM tag.
KEY_BYTES = 32
NONCE_BYTES = 32
TAG_BYTES = 16
#: Counters stay JavaScript-safe integers (the header carries them as JSON numbers).
_MAX_COUNTER = 2**53 - 1


def _version() -> str:
    from icbtool import __version__

    return __version__


def _primitives() -> tuple[Any, Any, Any, Any]:
    """(x25519 module, HKDF class, hashes module, AESGCM class), from ``cryptography``."""
    purpose = "the encrypted ICB protocol"
    x25519 = require("cryptography.hazmat.primitives.asymmetric.x25519", purpose)
    hkdf = require("cryptography.hazmat.primitives.kdf.hkdf", purpose)
    hashes = require("cryptography.hazmat.primitives.hashes", purpose)
    aead = require("cryptography.hazmat.primitives.ciphers.aead", purpose)
    return x25519, hkdf.HKDF, hashes, aead.AESGCM


def _token_bytes(token: str | bytes) -> bytes:
    t = token.encode("utf-8") if isinstance(token, str) else bytes(token)
    if not t:
        raise ValueError("the authentication token must not be empty")
    return t


def transcript(
    client_pub: bytes, client_nonce: bytes, server_pub: bytes, server_nonce: bytes, session: str
) -> bytes:
    """The bytes both sides authenticate (see the module docstring).

    Raises:
        ProtocolError: ``"bad_field"`` when a key or nonce has the wrong length.
    """
    for name, v, n in (
        ("client pub", client_pub, KEY_BYTES),
        ("client nonce", client_nonce, NONCE_BYTES),
        ("server pub", server_pub, KEY_BYTES),
        ("server nonce", server_nonce, NONCE_BYTES),
    ):
        if len(v) != n:
            raise ProtocolError("bad_field", f"handshake {name} must be {n} bytes, got {len(v)}")
    return (
        LABEL
        + b"\x00"
        + client_pub
        + client_nonce
        + server_pub
        + server_nonce
        + session.encode("utf-8")
    )


def auth_mac(auth_key: bytes, transcript_bytes: bytes) -> bytes:
    """HMAC-SHA256(auth key, transcript): what the client sends in ``auth.mac``; ``auth_key``
    from :func:`derive_auth_key` (it needs the shared secret: no offline guessing from a
    recorded handshake)."""
    return hmac.new(auth_key, transcript_bytes, hashlib.sha256).digest()


def _hkdf(shared: bytes, token: str | bytes, transcript_bytes: bytes, what: bytes) -> bytes:
    _, HKDF, hashes, _ = _primitives()
    ikm = shared + _token_bytes(token)
    salt = hashlib.sha256(transcript_bytes).digest()
    kdf = HKDF(algorithm=hashes.SHA256(), length=KEY_BYTES, salt=salt, info=LABEL + b" " + what)
    return bytes(kdf.derive(ikm))


def derive_keys(shared: bytes, token: str | bytes, transcript_bytes: bytes) -> tuple[bytes, bytes]:
    """The (client-to-server, server-to-client) AES-256-GCM keys.

    HKDF-SHA256 with ikm = ``shared | token``, salt = SHA-256(transcript), info =
    ``"icbtool/net/v1 c2s"`` / ``"icbtool/net/v1 s2c"``, 32 bytes each.
    """
    return (
        _hkdf(shared, token, transcript_bytes, b"c2s"),
        _hkdf(shared, token, transcript_bytes, b"s2c"),
    )


def derive_auth_key(shared: bytes, token: str | bytes, transcript_bytes: bytes) -> bytes:
    """The key of ``auth.mac``: HKDF as :func:`derive_keys` with info ``"icbtool/net/v1 auth"``."""
    return _hkdf(shared, token, transcript_bytes, b"auth")


class Channel:
    """One side's sealing and opening of a session's messages (AES-256-GCM, one key per way).

    Thread-safe: the counter is taken under :attr:`lock` (an RLock that
    :func:`icbtool.net.protocol.encode` holds while it reads :attr:`next_counter` and seals).
    Messages must be *sent* in the order of their counters: the receiver rejects a counter that
    is not above the last one it accepted.

    Args:
        send_key: 32-byte key of the direction this side sends in.
        recv_key: 32-byte key of the direction it receives in.
        send_dir: 4-byte direction id of what it sends (:data:`CLIENT_TO_SERVER` for a client).
        recv_dir: 4-byte direction id of what it receives.
    """

    def __init__(self, send_key: bytes, recv_key: bytes, send_dir: bytes, recv_dir: bytes):
        if len(send_key) != KEY_BYTES or len(recv_key) != KEY_BYTES:
            raise ValueError("Channel keys must be 32 bytes")
        if len(send_dir) != 4 or len(recv_dir) != 4 or send_dir == recv_dir:
            raise ValueError("Channel direction ids must be two different 4-byte strings")
        _, _, _, AESGCM = _primitives()
        self._send = AESGCM(send_key)
        self._recv = AESGCM(recv_key)
        self._send_dir = send_dir
        self._recv_dir = recv_dir
        self._next = 0
        self._last_seen = -1
        self.lock = threading.RLock()
        self._recv_lock = threading.Lock()

    @property
    def next_counter(self) -> int:
        """The counter the next :meth:`seal` will use."""
        return self._next

    @property
    def last_seen(self) -> int:
        """The highest counter :meth:`open` accepted (-1: none yet)."""
        return self._last_seen

    def seal(self, payload: bytes, aad: bytes) -> tuple[int, bytes]:
        """Encrypt and authenticate ``payload`` (and ``aad``, sent in the clear).

        Returns:
            (counter, ciphertext | 16-byte tag).

        Raises:
            ProtocolError: ``"crypto"`` when the counter is exhausted (2^53 messages).
        """
        with self.lock:
            ctr = self._next
            if ctr > _MAX_COUNTER:
                raise ProtocolError(
                    "crypto", "message counter exhausted (2^53 messages); open a new session"
                )
            self._next = ctr + 1
            nonce = self._send_dir + struct.pack(">Q", ctr)
            return ctr, self._send.encrypt(nonce, bytes(payload), bytes(aad))

    def open(self, counter: int, ciphertext: bytes, aad: bytes) -> bytes:
        """Check and decrypt a sealed payload.

        Raises:
            ProtocolError: ``"replay"`` when ``counter`` is not above the last accepted one;
                ``"crypto"`` when the ciphertext, its tag, the aad or the counter were changed
                (or it was sealed with another key). A rejected message does not move the
                last accepted counter.
        """
        invalid_tag = require("cryptography.exceptions", "the encrypted ICB protocol").InvalidTag
        if isinstance(counter, bool) or not isinstance(counter, int) or counter < 0:
            raise ProtocolError(
                "crypto", f"message counter must be an integer >= 0, got {counter!r}"
            )
        if counter > _MAX_COUNTER:
            raise ProtocolError("crypto", f"message counter {counter} is over 2^53 - 1")
        with self._recv_lock:
            if counter <= self._last_seen:
                raise ProtocolError(
                    "replay",
                    f"message counter {counter} is not above the last "
                    f"accepted counter {self._last_seen} (replayed or reordered)",
                )
            if len(ciphertext) < TAG_BYTES:
                raise ProtocolError(
                    "crypto",
                    f"sealed payload of {len(ciphertext)} bytes is "
                    f"shorter than the {TAG_BYTES}-byte tag",
                )
            nonce = self._recv_dir + struct.pack(">Q", counter)
            try:
                plain = self._recv.decrypt(nonce, bytes(ciphertext), bytes(aad))
            except invalid_tag:
                raise ProtocolError(
                    "crypto",
                    f"message {counter} failed authentication: its "
                    "header or payload was changed, or the keys differ",
                ) from None
            self._last_seen = counter
            return plain


def _new_keypair() -> tuple[Any, bytes]:
    x25519, _, _, _ = _primitives()
    priv = x25519.X25519PrivateKey.generate()
    return priv, priv.public_key().public_bytes_raw()


def _exchange(priv: Any, peer_pub: bytes) -> bytes:
    x25519, _, _, _ = _primitives()
    try:
        shared = priv.exchange(x25519.X25519PublicKey.from_public_bytes(peer_pub))
    except ValueError as e:  # a low-order point gives the all-zero secret
        raise ProtocolError("crypto", f"key exchange failed: {e}") from None
    if shared == bytes(len(shared)):  # pragma: no cover - OpenSSL already refuses it
        raise ProtocolError("crypto", "key exchange gave the all-zero secret")
    return shared


def _field_bytes(fields: dict[str, Any], kind: str, name: str, n: int) -> bytes:
    if name not in fields or not isinstance(fields[name], str):
        raise ProtocolError("bad_field", f"{kind}.{name}: missing or not a string")
    raw = unb64(fields[name], f"{kind}.{name}")
    if len(raw) != n:
        raise ProtocolError("bad_field", f"{kind}.{name}: must decode to {n} bytes, got {len(raw)}")
    return raw


class ClientHandshake:
    """The client's side of the handshake.

    Example:
        >>> hs = ClientHandshake(token)  # doctest: +SKIP
        >>> send(Message("hello", hs.hello_fields()))
        >>> channel, auth = hs.finish(welcome.fields)
        >>> send(Message("auth", auth))

    Args:
        token: the shared secret (non-empty str or bytes); never sent.
    """

    def __init__(self, token: str | bytes) -> None:
        self._token = _token_bytes(token)
        self._priv, self.pub = _new_keypair()
        self.nonce = os.urandom(NONCE_BYTES)
        self.session: str | None = None

    def hello_fields(
        self, codecs: Sequence[str] | None = None, client: str | None = None
    ) -> dict[str, Any]:
        """The fields of the ``hello`` message.

        Args:
            codecs: the codecs this client decodes, by preference (default: every codec of
                :data:`icbtool.net.codec.CODECS`, the defaults first).
            client: software name and version (default ``"icbtool/<version>"``).
        """
        if codecs is None:
            from icbtool.net import codec

            first = [codec.DEFAULT_GI_CODEC, codec.DEFAULT_DEPTH_CODEC]
            codecs = list(dict.fromkeys(first + list(codec.CODECS)))
        return {
            "client": client if client is not None else f"icbtool/{_version()}",
            "pub": b64(self.pub),
            "nonce": b64(self.nonce),
            "codecs": list(codecs),
        }

    def finish(self, welcome_fields: dict[str, Any]) -> tuple[Channel, dict[str, Any]]:
        """Derive the session from the server's ``welcome``.

        Returns:
            (the client's channel, the fields of the ``auth`` message to send next).

        Raises:
            ProtocolError: ``"bad_field"`` (welcome fields missing or of the wrong size) or
                ``"crypto"`` (invalid server key).
        """
        spub = _field_bytes(welcome_fields, "welcome", "pub", KEY_BYTES)
        snonce = _field_bytes(welcome_fields, "welcome", "nonce", NONCE_BYTES)
        session = welcome_fields.get("session")
        if not isinstance(session, str):
            raise ProtocolError("bad_field", "welcome.session: missing or not a string")
        t = transcript(self.pub, self.nonce, spub, snonce, session)
        shared = _exchange(self._priv, spub)
        c2s, s2c = derive_keys(shared, self._token, t)
        self.session = session
        channel = Channel(c2s, s2c, CLIENT_TO_SERVER, SERVER_TO_CLIENT)
        return channel, {"mac": b64(auth_mac(derive_auth_key(shared, self._token, t), t))}


class ServerHandshake:
    """The server's side of the handshake (one per connection).

    Args:
        token: the shared secret clients must hold (non-empty str or bytes).
    """

    def __init__(self, token: str | bytes) -> None:
        self._token = _token_bytes(token)
        self._priv, self.pub = _new_keypair()
        self.nonce = os.urandom(NONCE_BYTES)
        self.session = secrets.token_urlsafe(12)
        self._transcript: bytes | None = None
        self._keys: tuple[bytes, bytes] | None = None
        self._auth_key = b""

    def welcome(self, hello_fields: dict[str, Any], server: str | None = None) -> dict[str, Any]:
        """The fields of the ``welcome`` answering a client's ``hello``.

        Raises:
            ProtocolError: ``"bad_field"`` (hello fields missing or of the wrong size) or
                ``"crypto"`` (invalid client key).
        """
        cpub = _field_bytes(hello_fields, "hello", "pub", KEY_BYTES)
        cnonce = _field_bytes(hello_fields, "hello", "nonce", NONCE_BYTES)
        t = transcript(cpub, cnonce, self.pub, self.nonce, self.session)
        shared = _exchange(self._priv, cpub)
        self._keys = derive_keys(shared, self._token, t)
        self._auth_key = derive_auth_key(shared, self._token, t)
        self._transcript = t
        return {
            "session": self.session,
            "pub": b64(self.pub),
            "nonce": b64(self.nonce),
            "server": server if server is not None else f"icbtool/{_version()}",
        }

    def verify(self, auth_fields: dict[str, Any]) -> Channel:
        """Check the client's ``auth`` and open the session.

        Returns:
            The server's channel.

        Raises:
            ProtocolError: ``"auth"`` when the mac is wrong (wrong token), malformed, or comes
                before :meth:`welcome`.
        """
        if self._transcript is None:
            raise ProtocolError("auth", "auth before hello: the handshake was not started")
        if self._keys is None:
            raise ProtocolError("auth", "auth repeated: this handshake already opened a session")
        mac = auth_fields.get("mac") if isinstance(auth_fields, dict) else None
        try:
            got = unb64(mac, "auth.mac") if isinstance(mac, str) else b""
        except ProtocolError:
            got = b""
        want = auth_mac(self._auth_key, self._transcript)
        if not hmac.compare_digest(got, want):
            raise ProtocolError("auth", "authentication failed: wrong token")
        c2s, s2c = self._keys
        self._keys = None  # one session per handshake
        return Channel(s2c, c2s, SERVER_TO_CLIENT, CLIENT_TO_SERVER)


__all__ = [
    "CLIENT_TO_SERVER",
    "SERVER_TO_CLIENT",
    "Channel",
    "ClientHandshake",
    "ServerHandshake",
    "auth_mac",
    "derive_auth_key",
    "derive_keys",
    "transcript",
]
