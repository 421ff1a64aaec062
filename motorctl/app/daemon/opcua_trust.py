"""The OPC UA server's trust list of client certificates (OPC 10000-4 6.1.3, OPC 10000-12 7.3),
on disk in ``PKI_DIR/trusted`` and ``PKI_DIR/rejected`` (docs/opcua.md); read by the server at
ActivateSession and changed by ``motorctl opcua list|trust|untrust``."""

from __future__ import annotations

import os

#: refused client certificates kept in PKI_DIR/rejected at most (the oldest go)
MAX_REJECTED = 64


def pki_dir(cfg, log_dir: str | None = None) -> str:
    """The trust list's folder: ``daemon.opcua.pki_dir``, else ``LOG_DIR/opcua`` (``log_dir``:
    the daemon's, when it was given on its command line)."""
    oc = cfg.daemon.opcua
    if oc is not None and oc.pki_dir:
        return oc.pki_dir
    return os.path.join(log_dir or cfg.daemon.log_dir, "opcua")


class TrustList:
    """The client certificates the server accepts (OPC 10000-4 6.1.3, 10000-12 7.3 "trust
    list"): ``PKI_DIR/trusted/`` holds them (DER or PEM, one per file; a certificate is trusted
    itself, not through an issuer), ``PKI_DIR/rejected/`` the ones refused, kept (at most
    :data:`MAX_REJECTED`, as ``<thumbprint>.der``) for the operator to accept. Thumbprints are
    the SHA-1 of the DER bytes in hex (OPC 10000-6 6.2.3, as UaExpert shows them). The folder is
    read again when ``trusted/`` changes: no restart."""

    def __init__(self, pki: str):
        self.pki = pki
        self.trusted_dir = os.path.join(pki, "trusted")
        self.rejected_dir = os.path.join(pki, "rejected")
        self._mtime = None
        self._thumbs: set[str] = set()

    @staticmethod
    def thumbprint(der: bytes) -> str:
        import hashlib
        return hashlib.sha1(der).hexdigest()

    @staticmethod
    def load(data: bytes):
        """An X.509 certificate from DER or PEM bytes. Raises ValueError."""
        from cryptography import x509
        if data.lstrip().startswith(b"-----BEGIN"):
            return x509.load_pem_x509_certificate(data)
        return x509.load_der_x509_certificate(data)

    def _files(self, folder: str):
        try:
            names = sorted(os.listdir(folder))
        except OSError:
            return
        for n in names:
            path = os.path.join(folder, n)
            try:
                with open(path, "rb") as f:
                    cert = self.load(f.read())
            except (OSError, ValueError):
                continue
            yield path, cert

    def trusted(self) -> set[str]:
        """The thumbprints of the trusted certificates (read again when the folder changed)."""
        from cryptography.hazmat.primitives.serialization import Encoding
        try:
            m = os.stat(self.trusted_dir).st_mtime_ns
        except OSError:
            m = None
        if m != self._mtime:
            self._mtime = m
            self._thumbs = {self.thumbprint(c.public_bytes(Encoding.DER)) for _, c in self._files(self.trusted_dir)}
        return self._thumbs

    def refusal(self, der: bytes) -> str:
        """Why a client certificate (DER) is refused: "" when it is trusted and within its
        validity, else "untrusted", "expired" or "not yet valid"."""
        import datetime as dt
        if self.thumbprint(der) not in self.trusted():
            return "untrusted"
        cert = self.load(der)
        now = dt.datetime.now(dt.timezone.utc)
        if now > cert.not_valid_after_utc:
            return "expired"
        if now < cert.not_valid_before_utc:
            return "not yet valid"
        return ""

    def reject(self, der: bytes) -> str:
        """Keep a refused certificate in ``rejected/`` (the oldest beyond MAX_REJECTED go).
        Returns its path ("" when it cannot be written)."""
        try:
            os.makedirs(self.rejected_dir, mode=0o700, exist_ok=True)
            path = os.path.join(self.rejected_dir, self.thumbprint(der) + ".der")
            if not os.path.exists(path):
                with open(path, "wb") as f:
                    f.write(der)
            else:
                os.utime(path)
            old = sorted(os.listdir(self.rejected_dir),
                         key=lambda n: os.stat(os.path.join(self.rejected_dir, n)).st_mtime_ns)
            for n in old[:max(0, len(old) - MAX_REJECTED)]:
                os.unlink(os.path.join(self.rejected_dir, n))
            return path
        except OSError:
            return ""

    def listing(self) -> list[dict]:
        """Every certificate of ``trusted/`` and ``rejected/``: {state, thumbprint, subject,
        uri (the application URI of its subjectAltName), not_after, path}."""
        from cryptography import x509
        from cryptography.hazmat.primitives.serialization import Encoding
        out = []
        for state, folder in (("trusted", self.trusted_dir), ("rejected", self.rejected_dir)):
            for path, c in self._files(folder):
                try:
                    uris = c.extensions.get_extension_for_class(x509.SubjectAlternativeName).value \
                        .get_values_for_type(x509.UniformResourceIdentifier)
                except x509.ExtensionNotFound:
                    uris = []
                out.append({"state": state, "thumbprint": self.thumbprint(c.public_bytes(Encoding.DER)),
                            "subject": c.subject.rfc4514_string(), "uri": uris[0] if uris else "",
                            "not_after": c.not_valid_after_utc.strftime("%Y-%m-%d"), "path": path})
        return out

    def trust(self, what: str) -> dict:
        """Trust a certificate: ``what`` is a file (DER or PEM) or the thumbprint (or its first
        8+ hex digits) of a rejected one. It is written to ``trusted/<thumbprint>.der`` and
        leaves ``rejected/``. Returns its :meth:`listing` entry. Raises ValueError (one line)."""
        der = self._resolve(what, self.rejected_dir, "rejected")
        os.makedirs(self.trusted_dir, mode=0o700, exist_ok=True)
        t = self.thumbprint(der)
        path = os.path.join(self.trusted_dir, t + ".der")
        with open(path, "wb") as f:
            f.write(der)
        try:
            os.unlink(os.path.join(self.rejected_dir, t + ".der"))
        except OSError:
            pass
        return next(e for e in self.listing() if e["thumbprint"] == t and e["state"] == "trusted")

    def untrust(self, what: str) -> int:
        """Remove a certificate (file or thumbprint) from ``trusted/``: the files removed.
        Raises ValueError (one line)."""
        t = self.thumbprint(self._resolve(what, self.trusted_dir, "trusted"))
        gone = [e["path"] for e in self.listing() if e["state"] == "trusted" and e["thumbprint"] == t]
        for p in gone:
            os.unlink(p)
        return len(gone)

    def _resolve(self, what: str, folder: str, state: str) -> bytes:
        from cryptography.hazmat.primitives.serialization import Encoding
        if os.path.isfile(what):
            try:
                with open(what, "rb") as f:
                    return self.load(f.read()).public_bytes(Encoding.DER)
            except (OSError, ValueError) as exc:
                raise ValueError(f"{what}: not an X.509 certificate (DER or PEM): {exc}") from None
        w = what.lower().replace(":", "")
        if len(w) < 8 or any(c not in "0123456789abcdef" for c in w):
            raise ValueError(f"{what}: neither a certificate file nor a thumbprint (8 or more hex digits) "
                             f"of a {state} certificate")
        hits = {e["thumbprint"]: e["path"] for e in self.listing()
                if e["state"] == state and e["thumbprint"].startswith(w)}
        if len(hits) != 1:
            raise ValueError(f"{what}: {'no' if not hits else 'more than one'} {state} certificate with that "
                             f"thumbprint in {folder}; `motorctl opcua list` shows them")
        with open(next(iter(hits.values())), "rb") as f:
            return self.load(f.read()).public_bytes(Encoding.DER)




__all__ = ["TrustList", "pki_dir", "MAX_REJECTED"]
