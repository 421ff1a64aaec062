"""The OPC UA server (docs/opcua.md, OPC 40502): one daemon on the simulated gantry with
``daemon.opcua`` on a free loopback port and a users file (an operator, a viewer); checked with
asyncua's own client and its command-line tools (uals, uaread) run by this interpreter. Rates
are counted on the master's clock (the values' SourceTimestamp is the loop's time), never
raced against the wall; every wait is bounded."""

from __future__ import annotations

import asyncio
import importlib.util
import json
import os
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest
import yaml

from harness import free_port
from test_daemon_helpers import make_config, running_daemon, status, to_command_mode, wait_for

asyncua = pytest.importorskip("asyncua")
from asyncua import Client, ua  # noqa: E402

from motorctl.app.daemon.opcua_server import CNC_NS, main as check_main  # noqa: E402
from motorctl.app.users import hash_password  # noqa: E402

OPERATOR, VIEWER = ("olga", "op-secret"), ("victor", "view-secret")
AXES = "CncInterface.CncAxisList"
CHANNEL = "CncInterface.CncChannelList.CncChannel"
#: the server is up once it answers; this many connection attempts at most (0.2 s apart: its
#: start, asyncua's standard address space, takes 2-10 s of a loaded 2-core host)
MAX_CONNECTS = 300
#: notifications counted per axis for the rate
N_UPDATES = 40
#: a client request's bound [s]
UA_TIMEOUT_S = 10
#: the daemon's daemon.max_program_bytes here, and the programs sent beyond it [bytes]
LIMIT, BEYOND = 1 << 20, 5_000_000
#: benchmarks/bench_upload.py: its raw clients (HTTP, the control socket, OPC UA chunks)
_spec = importlib.util.spec_from_file_location(
    "bench_upload", Path(__file__).resolve().parents[1] / "benchmarks" / "bench_upload.py")
bench_upload = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench_upload)

#: open62541's client: the ``o6`` wheel from PyPI (built on open62541; Debian 12 has no
#: open62541 package) in a virtual environment of its own, ``.venv/o6`` (.ci/run installs it),
#: or the interpreter named by $MOTORCTL_O6_PYTHON
REPO = Path(__file__).resolve().parents[1]
O6_PYTHON = os.environ.get("MOTORCTL_O6_PYTHON") or str(REPO / ".venv" / "o6" / "bin" / "python")
O6_MISSING = "" if os.path.isfile(O6_PYTHON) and (
    "MOTORCTL_O6_PYTHON" in os.environ or list((REPO / ".venv" / "o6" / "lib").glob("python3*/site-packages/o6"))) \
    else f"no open62541 client: {O6_PYTHON} with the o6 wheel (python3 -m venv .venv/o6; .venv/o6/bin/pip install o6)"
#: the client's three attempts, each answered as one JSON line: the first two after a line on
#: stdin, the third after another
O6_CLIENT = r"""
import asyncio, json, sys
import o6
url, d, user, password, server_cert = sys.argv[1:6]
NONE = "http://opcfoundation.org/UA/SecurityPolicy#None"
B256 = "http://opcfoundation.org/UA/SecurityPolicy#Basic256Sha256"
own = dict(username=user, password=password, certificate=d + "/o6_cert.der", privateKey=d + "/o6_key.pem",
           trustList=[server_cert], applicationUri="urn:motorctl:o6test")

async def attempt(name, plain=False, **kw):
    c = o6.Client(url, **own, **kw)
    if plain:
        c.config.authSecurityPolicyUri = NONE
    try:
        await asyncio.wait_for(c.connect(), 20)
        out = {"ok": True, "x": await c.read("ns=2;s=CncInterface.CncAxisList.X.PosDirect.ActPos")}
    except Exception as exc:
        out = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
    finally:
        try:
            await c.disconnect()
        except Exception:
            pass
    print(json.dumps({name: out}, default=str), flush=True)

async def main():
    sys.stdin.readline()
    await attempt("plain", plain=True, securityMode=1, allowNonePolicyPassword=True)
    await attempt("untrusted", securityMode=3, securityPolicy=B256)
    sys.stdin.readline()
    await attempt("trusted", securityMode=3, securityPolicy=B256)

asyncio.run(main())
"""

#: OPC 40502's Mandatory children (the OPC Foundation's Opc.Ua.CNC.NodeSet.xml 1.0.0) as a
#: generic client looks them up, by the type that declares them: BrowseName -> DataType ("i=N":
#: namespace 0, "cnc=N": the CNC namespace) or (DataType, the NodeSet's EngineeringUnits UnitId)
B, U32, D, S, NID, POS = "i=1", "i=7", "i=11", "i=12", "i=17", "cnc=3007"
NODESET = {
    "CncInterfaceType": {"VendorName": S, "VendorRevision": S, "Version": S},
    "CncDriveType": {"ActChannel": NID, "ActLoad": (D, 20529), "ActPower": (D, 5723220), "ActTorque": (D, 20053),
                     "CmdTorque": (D, 20053), "IsInactive": B, "IsVirtual": B},
    "CncAxisType": {"ActStatus": "cnc=3004", "IsReferenced": B, "IsRotational": B, "PosDirect": POS,
                    "PosIndirect": POS, "ZeroOffset": (D, 5066068)},
    "CncChannelType": {
        "ActFeedrate": (D, 4732977), "ActGFunctions": U32, "ActJogIncrement": (D, 5066068), "ActMainProgramFile": S,
        "ActMainProgramName": S, "ActMFunctions": U32, "ActModalOffsetFunction": U32, "ActOperationMode": "cnc=3006",
        "ActOverride": (D, 20529), "ActProgramBlock": S, "ActProgramFile": S, "ActProgramName": S,
        "ActProgramStatus": "cnc=3002", "ActStatus": "cnc=3003", "BlockMode": B, "CmdFeedrate": (D, 4732977),
        "CmdOperationMode": "cnc=3006", "CmdOverride": (D, 20529), "DryRunFeed": (D, 4732977), "FeedHold": B,
        "Id": U32, "ToolId": U32, **{f"PosTcp{f}{c}": POS for f in ("Bcs", "Wcs") for c in "ABCXYZ"}}}
#: the types' NodeIds in the CNC namespace, and the objects of each here (CncAxisType: its
#: supertype CncDriveType's children too)
TYPES = {"CncInterfaceType": 1007, "CncDriveType": 1003, "CncAxisType": 1004, "CncChannelType": 1002}
OBJECTS = {"CncInterface": ("CncInterfaceType",), f"{AXES}.X": ("CncAxisType", "CncDriveType"),
           f"{AXES}.Y": ("CncAxisType", "CncDriveType"), CHANNEL: ("CncChannelType",)}
#: a CncPositionVariable's Mandatory children: its figures, and its EngineeringUnits and EURange
#: (named in the CNC namespace by the NodeSet); an AnalogItem's EURange (namespace 0)
POSITION = {"ActPos": D, "CmdPos": D, "RemDist": D, "EngineeringUnits": "i=887", "EURange": "i=884"}
#: what docs/opcua.md says the daemon does not have: BadNotSupported
NOT_SUPPORTED = {"ActPower", "ActTorque", "CmdTorque", "ActGFunctions", "ActMFunctions", "ActJogIncrement",
                 "ActProgramBlock", "DryRunFeed", *(f"PosTcp{f}{c}" for f in ("Bcs", "Wcs") for c in "ABCZ")}


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("opcua")
    users = tmp / "users.yaml"
    users.write_text(yaml.safe_dump({"users": {
        OPERATOR[0]: {"password": hash_password(OPERATOR[1]), "roles": ["operator"]},
        VIEWER[0]: {"password": hash_password(VIEWER[1]), "roles": ["viewer"]}}}))
    port, page = free_port(), free_port()
    url = f"opc.tcp://127.0.0.1:{port}/motorctl"
    with running_daemon(tmp, extra_daemon={"opcua": {"endpoint": url, "anonymous": "read"},
                                           "users_file": str(users), "motion_lead_s": 1.5,
                                           "scope": {"listen": f"127.0.0.1:{page}"},
                                           "max_program_bytes": LIMIT}) as d:
        d.url, d.tmp, d.page = url, tmp, page
        wait_for(lambda: status(d.sock)["process"].get("opcua_pid"), 20, "the OPC UA process")
        _run(_until_served(url))
        # uals starts now (interpreter and asyncua imports take seconds on a loaded host) and is
        # read by the last test, while the others run
        d.uals = _tool("uals", url, "-n", f"ns=2;s={AXES}", "-l", "-d", "2")
        to_command_mode(d.sock)              # both axes held by the servo: positions steady
        yield d
        if d.uals.poll() is None:
            d.uals.kill()
        d.uals.communicate(timeout=10)


def _o6_client(url: str, tmp: Path) -> subprocess.Popen:
    """open62541's client (O6_CLIENT) with a client certificate of its own made in ``tmp``,
    started: its attempts wait for a line on its stdin."""
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID
    _run(setup_self_signed_certificate(tmp / "o6_key.pem", tmp / "o6_cert.der", "urn:motorctl:o6test",
                                       "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "o6test"}))
    with open(tmp / "o6.err", "w") as err:           # its log lines: not read while it runs
        return subprocess.Popen([O6_PYTHON, "-c", O6_CLIENT, url, str(tmp), *OPERATOR,
                                 str(tmp / "logs" / "opcua" / "server_cert.der")], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=err, text=True)


def _tool(name: str, url: str, *args) -> subprocess.Popen:
    """asyncua's command-line tool ``name`` run by this interpreter (never through PATH)."""
    return subprocess.Popen([sys.executable, "-c", f"from asyncua.tools import {name}; {name}()",
                             "-u", url, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _run(coro):
    return asyncio.run(asyncio.wait_for(coro, 60))


async def _until_served(url: str) -> None:
    for _ in range(MAX_CONNECTS):
        try:
            async with Client(url, timeout=UA_TIMEOUT_S) as c:
                ns = await c.get_namespace_index(CNC_NS)
                assert ns == 2                 # the tools' node ids say ns=2
                if (await c.get_node(f"ns=2;s={CHANNEL}.Id").read_value()) == 1:
                    v = await c.get_node(f"ns=2;s=CncInterface.LoopCycles").read_value()
                    if v:
                        return
        except (OSError, asyncio.TimeoutError, ua.UaError):
            pass
        await asyncio.sleep(0.2)
    raise AssertionError(f"the OPC UA server did not answer in {MAX_CONNECTS} attempts")


def _client(url: str, user: tuple | None = None) -> Client:
    c = Client(url, timeout=UA_TIMEOUT_S)
    if user is not None:
        c.set_user(user[0])
        c.set_password(user[1])
    return c


def test_both_positions_at_20_hz_and_more_on_the_masters_clock(daemon):
    """Subscribe to X's and Y's ActPos (a notification per update: the trigger includes the
    timestamp); N_UPDATES of each span at most N_UPDATES / 20 s of the loop's time."""
    async def go():
        got: dict = {"X": [], "Y": []}

        class Handler:
            def datachange_notification(self, node, val, data):
                got[node.nodeid.Identifier.split(".")[-2]].append(data.monitored_item.Value.SourceTimestamp)

        async with _client(daemon.url) as c:
            sub = await c.create_subscription(10, Handler())
            nodes = [c.get_node(f"ns=2;s={AXES}.{a}.ActPos") for a in ("X", "Y")]
            flt = ua.DataChangeFilter(Trigger=ua.DataChangeTrigger.StatusValueTimestamp)
            await sub._subscribe(nodes, mfilter=flt, queuesize=1000)
            for _ in range(200):                       # 20 s at most
                if min(len(v) for v in got.values()) > N_UPDATES:
                    break
                await asyncio.sleep(0.1)
            await sub.delete()
        return got

    got = _run(go())
    for a, ts in got.items():
        assert len(ts) > N_UPDATES, (a, len(ts))
        ts = ts[1:N_UPDATES + 1]                        # the first is the value at subscription
        span = (ts[-1] - ts[0]).total_seconds()
        assert all(t1 > t0 for t0, t1 in zip(ts, ts[1:])), a
        rate = (len(ts) - 1) / span
        assert rate >= 20.0, (a, rate)


def test_an_operator_runs_a_program_through_the_methods(daemon):
    prog = "G21 G90\nG0 X5 Y5\nG1 X15 F3000\nG1 Y12\nG1 X10 Y8\nM2\n"

    async def go():
        async with _client(daemon.url, OPERATOR) as c:
            ch = c.get_node(f"ns=2;s={CHANNEL}")
            m = {n: c.get_node(f"ns=2;s={CHANNEL}.{n}") for n in ("Enable", "LoadProgram", "Start")}
            await ch.call_method(m["Enable"], "")
            for _ in range(100):
                if all([await c.get_node(f"ns=2;s={AXES}.{a}.Phase").read_value() == "command"
                        for a in ("X", "Y")]):
                    break
                await asyncio.sleep(0.1)
            with pytest.raises(ua.uaerrors.BadNotFound):          # only G-code files by path
                await ch.call_method(m["Start"], "/etc/hostname")
            why = await c.get_node(f"ns=2;s={CHANNEL}.LastCommandError").read_value()
            assert "not a G-code file" in why, why
            await ch.call_method(m["LoadProgram"], "square.ngc", prog)
            await ch.call_method(m["Start"], "square.ngc")
            seen, st = set(), None
            for _ in range(300):                           # 30 s at most
                st = await c.get_node(f"ns=2;s={CHANNEL}.ActProgramStatus").read_value()
                seen.add(st)
                if 1 in seen and st == 0:
                    break
                await asyncio.sleep(0.1)
            name = await c.get_node(f"ns=2;s={CHANNEL}.ActProgramName").read_value()
            x = await c.get_node(f"ns=2;s={AXES}.X.ActPos").read_value()
            y = await c.get_node(f"ns=2;s={AXES}.Y.ActPos").read_value()
            return seen, st, name, x, y

    seen, st, name, x, y = _run(go())
    assert 1 in seen and st == 0, seen                      # Running, then Stopped
    assert name == "square.ngc"
    wait_for(lambda: status(daemon.sock)["motion"]["idle"], 10, "the program's end")
    ax = status(daemon.sock)["axes"]
    assert abs(ax["X"]["y_m"] - 0.010) < 5e-6 and abs(ax["Y"]["y_m"] - 0.008) < 5e-6, ax
    assert abs(x - 0.010) < 2e-5 and abs(y - 0.008) < 2e-5
    assert not ax["X"]["fault"] and not ax["Y"]["fault"]


@pytest.mark.parametrize("who", ["anonymous", "viewer"])
def test_anonymous_and_viewer_may_read_but_not_call(daemon, who):
    async def go():
        async with _client(daemon.url, VIEWER if who == "viewer" else None) as c:
            v = await c.get_node(f"ns=2;s={AXES}.Y.ActPos").read_value()
            ch = c.get_node(f"ns=2;s={CHANNEL}")
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await ch.call_method(c.get_node(f"ns=2;s={CHANNEL}.Hold"))
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await ch.call_method(c.get_node(f"ns=2;s={CHANNEL}.Start"), "square.ngc")
            return v

    assert isinstance(_run(go()), float)
    assert status(daemon.sock)["motion"]["hold"] is False


def test_a_wrong_password_is_refused_and_a_user_added_to_the_file_logs_in(daemon):
    """The users file is read again when its modification time changes (no restart)."""
    users = daemon.tmp / "users.yaml"
    d = yaml.safe_load(users.read_text())
    d["users"]["nina"] = {"password": hash_password("nina-secret"), "roles": ["viewer"]}

    async def go():
        with pytest.raises(ua.uaerrors.BadUserAccessDenied):
            async with _client(daemon.url, (OPERATOR[0], "not-it")):
                pass
        with pytest.raises(ua.uaerrors.BadUserAccessDenied):
            async with _client(daemon.url, ("nina", "nina-secret")):
                pass
        st = users.stat()
        users.write_text(yaml.safe_dump(d))
        os.utime(users, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))   # a new mtime, surely
        async with _client(daemon.url, ("nina", "nina-secret")) as c:
            return await c.get_node(f"ns=2;s={AXES}.X.ActPos").read_value()

    assert isinstance(_run(go()), float)


def test_a_bad_users_file_is_one_line_and_exit_2(tmp_path, capsys):
    bad = tmp_path / "users.yaml"
    bad.write_text("users: {olga: {password: plain, roles: [operator]}}\n")
    cfg = make_config(tmp_path, extra_daemon={"opcua": {}, "users_file": str(bad)})
    assert check_main([str(cfg)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "daemon.users_file" in err and "password" in err, err
    # anonymous off without a users file: nobody could log in (the same check on the model)
    from motorctl.app.daemon.opcua_server import OpcuaConfigError, check_config
    from motorctl.config import OpcuaConfig, load_config
    c = load_config(cfg).cfg
    c = c.model_copy(update={"daemon": c.daemon.model_copy(
        update={"users_file": None, "opcua": OpcuaConfig(anonymous="off")})})
    with pytest.raises(OpcuaConfigError, match="anonymous: off"):
        check_config(c)

def test_basic256sha256_needs_a_trusted_client_certificate(daemon, tmp_path, capsys):
    """GetEndpoints offers None and Basic256Sha256 Sign and SignAndEncrypt, all with the
    certificate the server made at its first start (LOG_DIR/opcua). A client certificate not in
    the trust list is refused (BadCertificateUntrusted) and kept in rejected/, where `motorctl
    opcua list` shows it; once `motorctl opcua trust THUMBPRINT` accepted it, an operator reads
    and calls on a SignAndEncrypt session."""
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    from motorctl.cli import main as cli

    pki = daemon.tmp / "logs" / "opcua"
    made = pki / "server_cert.der"
    assert made.is_file() and (pki / "server_key.pem").is_file()
    key, cert = tmp_path / "client_key.pem", tmp_path / "client_cert.der"

    async def refused():
        await setup_self_signed_certificate(key, cert, "urn:motorctl:test", "localhost",
                                            [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "test"})
        async with _client(daemon.url) as c:
            eps = await c.get_endpoints()
        c = _client(daemon.url, OPERATOR)
        await c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{cert},{key}")
        with pytest.raises(ua.uaerrors.BadCertificateUntrusted):
            async with c:
                pass
        return eps

    async def accepted():
        c = _client(daemon.url, OPERATOR)
        await c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{cert},{key}")
        async with c:
            x = await c.get_node(f"ns=2;s={AXES}.X.ActPos").read_value()
            ch = c.get_node(f"ns=2;s={CHANNEL}")
            await ch.call_method(c.get_node(f"ns=2;s={CHANNEL}.SetFeedOverride"), 100.0)
        return x

    eps = _run(refused())
    got = {(e.SecurityPolicyUri.rsplit("#", 1)[-1], e.SecurityMode.name) for e in eps}
    assert got == {("None", "None_"), ("Basic256Sha256", "Sign"), ("Basic256Sha256", "SignAndEncrypt")}, got
    assert all(e.ServerCertificate == made.read_bytes() for e in eps if e.SecurityMode.name != "None_")
    # every endpoint asks for the password encrypted with the server's certificate
    assert {t.SecurityPolicyUri.rsplit("#", 1)[-1] for e in eps for t in e.UserIdentityTokens
            if t.TokenType == ua.UserTokenType.UserName} == {"Basic256Sha256"}
    capsys.readouterr()
    assert cli(["opcua", "list", "--pki-dir", str(pki)]) == 0
    rejected = [ln.split("\t") for ln in capsys.readouterr().out.splitlines() if ln.startswith("rejected")]
    assert len(rejected) == 1 and "CN=test" in rejected[0][2] and rejected[0][3] == "urn:motorctl:test", rejected
    assert cli(["opcua", "trust", rejected[0][1][:16], "--pki-dir", str(pki)]) == 0
    assert not list((pki / "rejected").iterdir())
    assert isinstance(_run(accepted()), float)
    assert cli(["opcua", "trust", "nothing-like-it", "--pki-dir", str(pki)]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_a_password_in_clear_is_refused(daemon):
    """A client that sends the password unencrypted on the None channel (the token policy asks
    for Basic256Sha256) is refused before the password is checked, the right password too."""
    class PlainClient(Client):
        def _add_user_auth(self, params, username, password):
            params.UserIdentityToken = ua.UserNameIdentityToken(
                UserName=username, Password=password.encode(), PolicyId="username")

    async def go():
        c = PlainClient(daemon.url, timeout=UA_TIMEOUT_S)
        c.set_user(OPERATOR[0])
        c.set_password(OPERATOR[1])
        with pytest.raises(ua.uaerrors.BadIdentityTokenRejected):
            async with c:
                pass

    _run(go())


def test_a_locked_name_is_refused_until_the_operator_unlocks_it(daemon, capsys):
    """Six wrong passwords within a minute (written through the daemon's own login state, on a
    clock of the test's: no waiting out the back-off) lock the name on the server: its right
    password is refused until `motorctl users unlock NAME`."""
    from motorctl.app.login import LOCK_AFTER, LoginGuard, state_path
    from motorctl.app.users import load_users
    from motorctl.cli import main as cli

    users = load_users(str(daemon.tmp / "users.yaml"))
    t = [__import__("time").time()]
    guard = LoginGuard(state_path(str(daemon.sock)), 3600.0, "test", clock=lambda: t[0])
    for i in range(LOCK_AFTER):
        t[0] += 9.0                                   # 6 failures in 54 s, beyond each back-off
        v = guard.attempt(users, VIEWER[0], "wrong", f"192.0.2.{i}")
    assert v.why == "locked", v

    async def login():
        async with _client(daemon.url, VIEWER) as c:
            return await c.get_node(f"ns=2;s={AXES}.X.ActPos").read_value()

    with pytest.raises(ua.uaerrors.BadUserAccessDenied):
        _run(login())
    assert cli(["--socket", str(daemon.sock), "users", "unlock", VIEWER[0]]) == 0
    assert "unlocked" in capsys.readouterr().out
    assert isinstance(_run(login()), float)


def test_a_generic_client_finds_the_cnc_objects_by_the_nodesets_type_nodeids(daemon):
    """As an OPC 40502 client knows them (the OPC Foundation's Opc.Ua.CNC.NodeSet.xml: namespace
    http://opcfoundation.org/UA/CNC, CncInterfaceType i=1007, CncAxisListType i=1008,
    CncSpindleListType i=1009, CncChannelListType i=1010, CncAxisType i=1004 under CncDriveType
    i=1003 under CncComponentType i=1001, CncPositionVariableType i=2001, CncAxisStatus i=3004):
    the objects are found by their type definitions alone, the positions under PosDirect with
    their EngineeringUnits (metre), the status variables of the enumeration DataTypes."""
    async def go():
        async with _client(daemon.url) as c:
            ns = await c.get_namespace_index("http://opcfoundation.org/UA/CNC")

            async def typed(parent, num):
                return [o for o in await parent.get_children()
                        if await o.read_type_definition() == ua.NodeId(num, ns)]

            iface, = await typed(c.nodes.objects, 1007)
            lists = {n: await typed(iface, n) for n in (1008, 1009, 1010)}
            axes = await typed(lists[1008][0], 1004)
            spindles = await typed(lists[1009][0], 1005)
            chans = await typed(lists[1010][0], 1002)
            supers, n = [], c.get_node(ua.NodeId(1004, ns))
            while n.nodeid != ua.NodeId(ua.ObjectIds.BaseObjectType):
                n = c.get_node((await n.get_references(ua.ObjectIds.HasSubtype, ua.BrowseDirection.Inverse))[0].NodeId)
                supers.append(n.nodeid)
            x = axes[0]
            pos, = [p for p in await typed(x, 2001) if (await p.read_browse_name()).Name == "PosDirect"]
            act = await pos.get_child(f"{ns}:ActPos")
            eu = await (await pos.get_child(f"{ns}:EngineeringUnits")).read_value()
            status = await x.get_child(f"{ns}:ActStatus")
            return (len(lists[1008]), len(lists[1009]), len(lists[1010]), [(await a.read_browse_name()).Name for a in axes],
                    len(spindles), len(chans), supers, (await pos.read_browse_name()).Name, await act.read_value(),
                    eu.UnitId, await status.read_data_type(), await (await x.get_child(f"{ns}:ActPos")).read_value())

    (n_axl, n_spl, n_chl, axes, n_sp, n_ch, supers, pos_name, act, unit, status_dt, act_axis) = _run(go())
    assert (n_axl, n_spl, n_chl) == (1, 1, 1) and axes == ["X", "Y"] and n_sp == 0 and n_ch == 1
    assert supers[:2] == [ua.NodeId(1003, 2), ua.NodeId(1001, 2)], supers
    assert pos_name == "PosDirect" and unit == 5067858            # UNECE MTR: metre
    assert abs(act - act_axis) < 1e-4                             # the same measured position
    assert status_dt == ua.NodeId(3004, 2)


def test_every_mandatory_child_of_the_nodesets_types_is_served(daemon):
    """A generic client walks OPC 40502's Mandatory children (NODESET, from the NodeSet) on the
    objects (CncInterface, X and Y, CncChannel) by their browse paths, in one request each:
    every one is there with the NodeSet's DataType and EngineeringUnits, each AnalogItem with its
    EURange, each CncPositionVariable with its own children; every value is Good but those
    docs/opcua.md lists as BadNotSupported; and the types carry each child as an instance
    declaration with ModellingRule Mandatory."""
    async def go():
        async with _client(daemon.url) as c:
            ns = await c.get_namespace_index("http://opcfoundation.org/UA/CNC")
            dt = {"i": lambda n: ua.NodeId(int(n)), "cnc": lambda n: ua.NodeId(int(n), ns)}

            def want(spec):
                kind, _, n = (spec[0] if isinstance(spec, tuple) else spec).partition("=")
                return dt[kind](n)

            rows = []                     # (start node, path, DataType, UnitId or None, figure)
            for obj, types in OBJECTS.items():
                start = ua.NodeId(obj, ns)
                for t in types:
                    for name, spec in NODESET[t].items():
                        unit = spec[1] if isinstance(spec, tuple) else None
                        rows.append((start, f"/{ns}:{name}", want(spec), None, name))
                        if unit is not None:
                            rows.append((start, f"/{ns}:{name}/0:EngineeringUnits", ua.NodeId(887), unit, name))
                            rows.append((start, f"/{ns}:{name}/0:EURange", ua.NodeId(884), None, name))
                        if spec == POS:
                            rows += [(start, f"/{ns}:{name}/{ns}:{k}", want(v), None, name) for k, v in POSITION.items()]
                for t in types:                    # the type's own declarations
                    rows += [(ua.NodeId(TYPES[t], ns), f"/{ns}:{name}", want(spec), "declaration", name)
                             for name, spec in NODESET[t].items()]
            found = []
            for start in dict.fromkeys(r[0] for r in rows):
                mine = [r for r in rows if r[0] == start]
                res = await c.translate_browsepaths(start, [r[1] for r in mine])
                found += [(r, p.Targets[0].TargetId if p.StatusCode.is_good() and p.Targets else None)
                          for r, p in zip(mine, res)]
            missing = [f"{r[0].Identifier}{r[1]}" for r, n in found if n is None]
            nodes = [c.get_node(n) for _, n in found if n is not None]
            kinds = await c.read_attributes(nodes, ua.AttributeIds.DataType)
            values = await c.read_attributes(nodes, ua.AttributeIds.Value)
            browsed = await c.browse_nodes([c.get_node(n) for r, n in found if n is not None and r[3] == "declaration"])
            return ns, missing, [(r, k.Value.Value, v) for (r, n), k, v in zip([f for f in found if f[1] is not None],
                                                                               kinds, values)], browsed

    ns, missing, got, browsed = _run(go())
    assert not missing, missing
    wrong = [(r[0].Identifier, r[1], k, r[2]) for r, k, _ in got if k != r[2]]
    assert not wrong, wrong
    units = [(r[0].Identifier, r[1], v.Value.Value.UnitId) for r, _, v in got
             if isinstance(r[3], int) and v.Value.Value.UnitId != r[3]]
    assert not units, units
    figures = [(r, v) for r, _, v in got if r[3] is None and r[1].count("/") == 1 or r[1].endswith(
        ("ActPos", "CmdPos", "RemDist"))]
    bad = sorted({r[4] for r, v in figures if not v.StatusCode.is_good()})
    assert set(bad) == NOT_SUPPORTED, bad
    assert all(v.StatusCode.name == "BadNotSupported" for r, v in figures if r[4] in NOT_SUPPORTED)
    rules = [[ref.NodeId for ref in res.References if ref.ReferenceTypeId == ua.NodeId(ua.ObjectIds.HasModellingRule)]
             for _, res in browsed]
    assert all(r == [ua.NodeId(ua.ObjectIds.ModellingRule_Mandatory)] for r in rules), rules


def test_a_program_beyond_the_limit_is_refused_at_once_and_the_next_one_runs(daemon):
    """daemon.max_program_bytes is 1 MiB here; 5 MB of G-code go to every surface that takes a
    program, by raw clients that send and read at once (benchmarks/bench_upload.py's, which
    streams 2 GB the same way): the operator page's upload with a Content-Length is answered 413
    naming the limit (the daemon refused it when it was announced) and without one 411; the
    control socket refuses an ``upload`` of that size by name and a ``gcode`` request line
    beyond its 64 KiB; the OPC UA server answers a request streamed beyond its limit with
    BadRequestTooLarge and closes the connection. After each surface's refusals a 5 mm square
    sent the same way runs to its end point."""
    import http.client
    base = ("127.0.0.1", daemon.page)
    wait_for(lambda: _page_up(daemon.page), 30, "the operator page")
    h = http.client.HTTPConnection(*base, timeout=UA_TIMEOUT_S)
    h.request("POST", "/login", json.dumps({"name": OPERATOR[0], "password": OPERATOR[1]}),
              {"Content-Type": "application/json"})
    r = h.getresponse()
    auth = {"Cookie": r.getheader("Set-Cookie").split(";", 1)[0], "X-CSRF-Token": json.loads(r.read())["csrf"]}
    wait_for(lambda: status(daemon.sock)["motion"]["idle"], 10, "no motion")
    to_command_mode(daemon.sock)

    def ran(k: int) -> None:
        _, x, y = bench_upload.square(k)
        assert bench_upload.wait_end(str(daemon.sock), x, y, 30.0), (k, status(daemon.sock)["axes"])

    path = "/operator/program?name=huge.ngc"
    r = bench_upload.http_stream(*base, path, BEYOND, auth)
    assert r["status"] == 413 and f"max_program_bytes = {LIMIT}" in r["answer"]["error"], r
    r = bench_upload.http_stream(*base, path, BEYOND, auth, chunked=True)
    assert r["status"] == 411, r
    text, _, _ = bench_upload.square(1)
    h = http.client.HTTPConnection(*base, timeout=30)
    h.request("POST", "/operator/program?name=square1.ngc", text.encode(), auth)
    assert h.getresponse().status == 200
    ran(1)

    r = bench_upload.socket_stream(str(daemon.sock), BEYOND, "upload")
    assert f"max_program_bytes = {LIMIT}" in r["answer"]["error"], r
    r = bench_upload.socket_stream(str(daemon.sock), BEYOND, "line")
    assert r["answer"] == "closed" or "longer than" in r["answer"]["error"], r
    text, _, _ = bench_upload.square(2)
    assert ctl_program(daemon.sock, text, "square2.ngc")
    ran(2)

    r = _run(bench_upload.ua_stream(daemon.url, BEYOND, OPERATOR))
    assert r["error"] == "BadRequestTooLarge" and r["closed"], r
    text, _, _ = bench_upload.square(3)

    async def start():
        async with _client(daemon.url, OPERATOR) as c:
            ch = c.get_node(f"ns=2;s={CHANNEL}")
            await ch.call_method(c.get_node(f"ns=2;s={CHANNEL}.LoadProgram"), "square3.ngc", text)
            await ch.call_method(c.get_node(f"ns=2;s={CHANNEL}.Start"), "square3.ngc")
    _run(start())
    ran(3)


@pytest.mark.skipif(bool(O6_MISSING), reason=O6_MISSING)
def test_open62541s_client_needs_an_encrypted_password_and_a_trusted_certificate(daemon):
    """open62541's client (o6, its own interpreter): a password sent in clear on the None channel
    (the client told to: authSecurityPolicyUri None, allowNonePolicyPassword) is refused,
    BadIdentityTokenRejected; a Basic256Sha256 SignAndEncrypt session with a client certificate
    the server does not trust is refused, BadCertificateUntrusted, the certificate kept in
    rejected/; once `motorctl opcua trust` accepted it, the same client logs in and reads X's
    position."""
    from motorctl.app.daemon.opcua_trust import TrustList
    from motorctl.cli import main as cli
    pki, p = daemon.tmp / "logs" / "opcua", _o6_client(daemon.url, daemon.tmp)
    thumb = TrustList.thumbprint((daemon.tmp / "o6_cert.der").read_bytes())

    def answer() -> dict:                 # the client's next JSON line (o6 prints a banner first)
        for line in p.stdout:
            if line.startswith("{"):
                return json.loads(line)
        return {}

    def go() -> None:
        p.stdin.write("go\n")
        p.stdin.flush()

    try:
        go()
        got = {**answer(), **answer()}
        rejected = (pki / "rejected" / f"{thumb}.der").is_file()
        assert cli(["opcua", "trust", thumb[:16], "--pki-dir", str(pki)]) == 0
        go()
        got.update(answer())
        p.wait(60)
    finally:
        if p.poll() is None:
            p.kill()
    assert set(got) == {"plain", "untrusted", "trusted"}, (got, (daemon.tmp / "o6.err").read_text()[-2000:])
    assert not got["plain"]["ok"] and str(ua.StatusCodes.BadIdentityTokenRejected) in got["plain"]["error"], got
    assert not got["untrusted"]["ok"] and str(ua.StatusCodes.BadCertificateUntrusted) in got["untrusted"]["error"], got
    assert rejected
    assert got["trusted"]["ok"] and isinstance(got["trusted"]["x"], float), got


def _page_up(port: int) -> bool:
    try:
        return urllib.request.urlopen(f"http://127.0.0.1:{port}/operator/session", timeout=5).status == 200
    except OSError:
        return False


def ctl_program(sock, text: str, name: str) -> bool:
    from motorctl.client import send_program
    return bool(send_program(str(sock), text, name, 30.0).get("ok"))


def test_the_tools_browse_the_cnc_objects_and_read_a_position(daemon):
    out, err = daemon.uals.communicate(timeout=60)
    assert daemon.uals.returncode == 0, err
    for name in ("X", "Y", "ActPos", "CmdPos", "ActSpeed", "IsReferenced", "FaultReason", "TurnaroundP99"):
        assert f"2:{name}" in out, out
    wait_for(lambda: status(daemon.sock)["motion"]["idle"], 10, "no motion")
    r = subprocess.run([sys.executable, "-c", "from asyncua.tools import uaread; uaread()", "-u",
                        daemon.url, "-n", f"ns=2;s={AXES}.X.ActPos"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    x = float(r.stdout.strip())
    assert abs(x - status(daemon.sock)["axes"]["X"]["y_m"]) < 2e-5     # the axis held at rest


def test_start_by_path_reads_a_regular_file_up_to_the_limit_only(tmp_path):
    """Start's file: read up to daemon.max_program_bytes and no further (a file larger, or grown
    since, is refused with the limit's name), and only a regular file (a FIFO named .ngc is
    refused at once instead of blocking the read; a missing one is an OSError)."""
    from motorctl.app.daemon.opcua_methods import read_program
    ok = tmp_path / "a.ngc"
    ok.write_text("G0 X1\nM2\n")
    assert read_program(str(ok), 100) == "G0 X1\nM2\n"
    big = tmp_path / "b.ngc"
    big.write_bytes(b"G0 X1\n" * 100)
    with pytest.raises(ValueError, match="max_program_bytes = 599"):
        read_program(str(big), 599)
    assert len(read_program(str(big), 600)) == 600
    fifo = tmp_path / "c.ngc"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match="not a regular file"):
        read_program(str(fifo), 100)
    with pytest.raises(OSError):
        read_program(str(tmp_path / "missing.ngc"), 100)

