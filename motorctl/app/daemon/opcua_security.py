"""Who may talk to the OPC UA server, and how much (docs/opcua.md "Security"): the user manager
over the users file and the login guard, the refusal of a password sent in clear, the trust
list's check of a channel's client certificate, the permission rules (only an operator calls,
nobody writes), the server's certificate, and the transport's bounds on what a client may send.

The transport (OPC 10000-6 7.1.2): asyncua buffers a chunk whole before it compares its size
with the negotiated receive buffer, and shares one set of limits among all connections, which
each client's Hello narrows for the others. :func:`server_class` gives every connection its own
limits, refuses a chunk larger than the receive buffer when its header arrives (before its
body is taken: BadTcpMessageTooLarge) and closes a connection whose message grew beyond the
message limit (BadRequestTooLarge, asyncua's chunk count), so that a client streaming a message
of gigabytes is answered at the limit and costs the server no more than the limit's memory.
A refused connection is closed as HTTP servers close one whose client is still sending (a
"lingering close"): the answer sent, the server's side shut (FIN), what still comes read and
dropped for at most :data:`LINGER_S`, then closed; a close with unread data would send a TCP reset
that can destroy the answer before the client has read it.
"""

from __future__ import annotations

import asyncio
import copy
import math
import os
import socket
import sys

from motorctl.app.daemon.opcua_trust import TrustList

#: the largest chunk a client may send [bytes] (asyncua's default receive buffer)
CHUNK_BYTES = 65535
#: what a request carries beside a program's text (headers, names, signatures) [bytes]
MESSAGE_OVERHEAD = 1 << 16
#: Bad_TcpMessageTooLarge (OPC 10000-4 7.34.2): a chunk beyond the receive buffer
BAD_TCP_MESSAGE_TOO_LARGE = 0x80080000
#: how long a refused connection's incoming data is still read and dropped [s] (module docstring)
LINGER_S = 2.0


def _mtime(path: str | None) -> int | None:
    try:
        return os.stat(path).st_mtime_ns if path else None
    except OSError:
        return None


def user_manager(users, anonymous: bool, guard=None, trust: TrustList | None = None):
    """asyncua's user manager over :class:`motorctl.app.users.Users` (OPC 10000-4 5.6.3):
    operator -> UserRole.User (may Call), viewer -> UserRole.Anonymous with its name (reads),
    no name -> anonymous when allowed; None (BadUserAccessDenied / BadIdentityTokenRejected)
    otherwise. Names and passwords go through ``guard`` (:class:`motorctl.app.login.LoginGuard`:
    back-off, lockout, journal) with the client's address that :func:`refuse_clear_passwords` noted; a
    channel's client certificate not in ``trust`` is refused (BadCertificateUntrusted), kept in
    its ``rejected/`` and journaled."""
    from asyncua import ua
    from asyncua.common.utils import ServiceError
    from asyncua.crypto.permission_rules import User, UserRole
    from asyncua.server.user_managers import UserManager

    from motorctl.app.login import JOURNAL
    from motorctl.app.users import UsersError, load_users

    class Users(UserManager):
        def __init__(self):
            self.users = users
            self.path = users.path if users is not None else None
            self.mtime = _mtime(self.path)
            self.peer = "?"                  # the address of the session being activated

        def check_certificate(self, der: bytes) -> None:
            """Raise ServiceError unless the channel's client certificate is trusted."""
            why = trust.refusal(der) if trust is not None else ""
            if not why:
                return
            try:
                c = TrustList.load(der)
                subject = c.subject.rfc4514_string()
            except ValueError:
                subject = "?"
            kept = trust.reject(der) if why == "untrusted" else ""
            JOURNAL.warning("OPC UA: client certificate refused (%s) from %s: %s, thumbprint %s%s", why,
                            self.peer, subject, TrustList.thumbprint(der),
                            f"; kept as {kept}: `motorctl opcua trust {TrustList.thumbprint(der)[:16]}` "
                            "accepts it" if kept else "")
            raise ServiceError(ua.StatusCodes.BadCertificateUntrusted if why == "untrusted"
                               else ua.StatusCodes.BadCertificateTimeInvalid)

        def current(self):
            """The users file, read again when its modification time changed (a file that has
            become wrong: no logins, one line on stderr)."""
            if self.path is None:
                return None
            m = _mtime(self.path)
            if m != self.mtime:
                self.mtime = m
                try:
                    self.users = load_users(self.path)
                except UsersError as exc:
                    self.users = None
                    sys.stderr.write(f"motorctl: warning: OPC UA logins off: {exc}\n")
            return self.users

        def get_user(self, iserver, username=None, password=None, certificate=None):
            peer, self.peer = self.peer, "?"
            if certificate:
                # the channel's client certificate (None on a None channel: _Factory), not an
                # X509 identity token (not offered)
                self.peer = peer
                self.check_certificate(certificate)
            if username is None:
                return User(role=UserRole.Anonymous) if anonymous else None
            now = self.current()
            if now is None or guard is None:
                JOURNAL.warning("login refused: %r from %s (OPC UA): logins are off", str(username)[:64], peer)
                return None
            try:
                v = guard.attempt(now, username, password, peer)
            except OSError as exc:
                JOURNAL.warning("login refused: %r from %s (OPC UA): the login state %s: %s", str(username)[:64],
                                peer, guard.path, exc.strerror or exc)
                return None
            if not v.ok:
                return None
            return User(role=UserRole.User if "operator" in v.roles else UserRole.Anonymous, name=username)

    return Users()


def refuse_clear_passwords(iserver, um) -> None:
    """Refuse a user name token whose password is not encrypted (OPC 10000-4 7.36.3: the token
    policy says Basic256Sha256, so a conforming client encrypts it with the server's
    certificate; a password in clear has crossed the network readable): BadIdentityTokenRejected
    before the name or the password is looked at, journaled. Notes the client's address for the
    user manager ``um`` (ActivateSession runs the two one after the other, without a wait)."""
    from asyncua import ua
    from asyncua.common.utils import ServiceError

    from motorctl.app.login import JOURNAL
    decrypt = iserver.decrypt_user_token

    def checked(isession, token):
        peer = isession.name[0] if isinstance(isession.name, tuple) and isession.name else str(isession.name)
        um.peer = str(peer)
        if not token.EncryptionAlgorithm:
            JOURNAL.warning("login refused: %r from %s (OPC UA): the password was sent in clear (not encrypted "
                            "with the server's certificate, as the user token policy asks)",
                            str(token.UserName)[:64], um.peer)
            raise ServiceError(ua.StatusCodes.BadIdentityTokenRejected)
        return decrypt(isession, token)

    iserver.decrypt_user_token = checked


def server_class(max_message_bytes: int):
    """asyncua's Server with its endpoints and its transport changed where it builds them:
    every user name token policy asks for the password encrypted with the server's certificate
    (Basic256Sha256; asyncua offers it in clear on a SignAndEncrypt channel); a None channel
    carries no client certificate (OPC 10000-4 7.1: ignored with SecurityPolicy None), so the
    user manager sees one only on Sign and SignAndEncrypt channels; a request is at most
    ``max_message_bytes`` and each connection is bounded on its own (module docstring)."""
    from asyncua import Server, ua
    from asyncua.crypto import security_policies as sp
    from asyncua.server import binary_server_asyncio as bsa

    class _Factory(sp.SecurityPolicyFactory):
        def create(self, peer_certificate):
            return super().create(None if self.mode == ua.MessageSecurityMode.None_ else peer_certificate)

    class Protocol(bsa.OPCUAProtocol):
        """One connection, with limits of its own; refused at its first chunk beyond them."""

        def __init__(self, *args, limits, **kw):
            super().__init__(*args, limits=copy.copy(limits), **kw)
            self.too_large = False
            self.lingering = False

        def connection_made(self, transport):
            super().connection_made(transport)
            conn = self.processor._connection
            receive = conn.receive_from_header_and_body

            def bounded(header, body):
                try:
                    return receive(header, body)
                except ua.uaerrors.BadRequestTooLarge:
                    self.too_large = True            # answered by the processor, then closed
                    raise

            conn.receive_from_header_and_body = bounded

        def data_received(self, data):
            if self.lingering or self.transport is None or self.transport.is_closing():
                return                               # dropped (module docstring)
            super().data_received(data)              # takes the whole chunks
            if len(self._buffer) >= 8 and int.from_bytes(self._buffer[4:8], "little") > self.limits.max_recv_buffer:
                self._buffer = b""
                from asyncua.ua.ua_binary import uatcp_to_binary
                why = f"a chunk larger than the receive buffer ({self.limits.max_recv_buffer} bytes)"
                self.transport.write(uatcp_to_binary(ua.MessageType.Error, ua.ErrorMessage(
                    ua.StatusCode(BAD_TCP_MESSAGE_TOO_LARGE), why)))
                self.linger()

        async def _process_one_msg(self, header, buf):
            await super()._process_one_msg(header, buf)
            if self.too_large and not self.lingering and not self.transport.is_closing():
                self.linger()

        def linger(self) -> None:
            """The answer written: the server's side shut, the client's data dropped until it
            closes or LINGER_S has passed, then the connection closed (module docstring)."""
            self.lingering = True
            tr = self.transport
            self._buffer = b""
            if tr.can_write_eof():
                tr.write_eof()
            asyncio.get_running_loop().call_later(LINGER_S, tr.abort)

    class Binary(bsa.BinaryServer):
        def _make_protocol(self):
            return Protocol(iserver=self.iserver, policies=self._policies, clients=self.clients,
                            closing_tasks=self.closing_tasks, limits=self.limits)

    class CncUaServer(Server):
        def __init__(self, *args, **kw):
            super().__init__(*args, **kw)
            self.limits.max_message_size = int(max_message_bytes)
            self.limits.max_chunk_count = math.ceil(max_message_bytes / (CHUNK_BYTES - 1024)) + 1

        async def _setup_server_nodes(self):
            await super()._setup_server_nodes()
            self._policies[:] = [_Factory(f.cls, f.mode, f.certificate, f.private_key, f.permission_ruleset)
                                 for f in self._policies]
            for edp in self.iserver.endpoints:
                for tok in edp.UserIdentityTokens:
                    if tok.TokenType == ua.UserTokenType.UserName:
                        tok.SecurityPolicyUri = sp.SecurityPolicyBasic256Sha256.URI

        async def start(self):
            import asyncua.server.server as srv
            srv.BinaryServer, plain = Binary, srv.BinaryServer     # built by start(): ours instead
            try:
                await super().start()
            finally:
                srv.BinaryServer = plain

    return CncUaServer


def ruleset():
    """Anonymous and viewer sessions: sessions, browse, read, subscriptions; an operator's also
    Call; nobody writes or changes the address space (OPC 10000-4 5.10.4, 5.7)."""
    from asyncua import ua
    from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, UserRole

    call = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
    write = ua.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary)
    read = {ua.NodeId(t) for t in USER_TYPES} - {call, write}

    class Rules(PermissionRuleset):
        def check_validity(self, user, action_type_id, body):
            if action_type_id in read:
                return True
            if action_type_id == call:
                return user is not None and user.role == UserRole.User
            return False

    return Rules()



async def certificate_files(cert: str | None, key: str | None, cert_dir: str, app_uri: str) -> tuple[str, str]:
    """The server's (certificate, key) files: the configured pair, or the self-signed one in
    ``cert_dir`` (RSA 2048, asyncua's helpers over ``cryptography``; made at the first start
    and kept)."""
    if cert is not None:
        return cert, key
    from pathlib import Path

    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID
    os.makedirs(cert_dir, mode=0o700, exist_ok=True)
    k, c = Path(cert_dir, "server_key.pem"), Path(cert_dir, "server_cert.der")
    await setup_self_signed_certificate(k, c, app_uri, socket.gethostname(),
                                        [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
                                        {"commonName": "motorctl", "organizationName": "motorctl"})
    return str(c), str(k)


__all__ = ["user_manager", "refuse_clear_passwords", "server_class", "ruleset", "certificate_files",
           "CHUNK_BYTES", "MESSAGE_OVERHEAD"]
