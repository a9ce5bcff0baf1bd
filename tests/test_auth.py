"""Bearer tokens bound to stream-ID prefixes: the token file, `phim auth add-token`, the safe-bind rule, and
a real uvicorn server that answers 401/403 before anything else, re-reads its token file on change, and
serves the clients that carry a token."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest
import torch
from pydantic import ValidationError
from server_helpers import default_detector, sector_msg, serve

from clients.base import ServerError
from clients.connect import ConnectConfig, make_client
from contract import ErrorCode, decode_response
from lidar.synthetic import synthetic_turn
from model.sectors import split_turn
from server.auth import TokenFile, TokenFileError, add_token, parse_tokens, token_hash
from server.settings import Settings


def sectors() -> list[np.ndarray]:
    """A synthetic turn's 4 sectors, 2,000 points each (quick forwards)."""
    return [s[:2000].contiguous().numpy() for s in split_turn(torch.from_numpy(synthetic_turn(seed=4)), 4)]


def test_add_token_stores_only_its_hash_owner_only(tmp_path: Path):
    path = tmp_path / "tokens.jsonl"
    token = add_token(path, "fleet-a.", note="depot 1")
    admin = add_token(path, "", admin=True)
    text = path.read_text()
    assert token not in text and admin not in text and token_hash(token) in text
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    table = TokenFile(path)
    grant = table.grant(token)
    assert grant is not None and grant.prefix == "fleet-a." and not grant.admin and grant.note == "depot 1"
    assert grant.allows("fleet-a.car-7") and not grant.allows("fleet-b.car-7")
    assert table.grant(admin).allows("anything") and table.grant("phim_wrong") is None


@pytest.mark.parametrize(
    ("line", "why"),
    [
        ("not json", "expected a JSON object"),
        ('{"prefix": "a."}', "expected a JSON object"),
        ('{"sha256": "abc", "prefix": "a."}', "64 lowercase hex"),
        (json.dumps({"sha256": "0" * 64, "prefix": ""}), "non-empty prefix"),
    ],
)
def test_a_bad_line_is_named(line: str, why: str):
    with pytest.raises(TokenFileError, match=f"f.jsonl:2: .*{why}"):
        parse_tokens("# comment\n" + line, "f.jsonl")


def test_rotation_without_restart_and_a_bad_rewrite_keeps_the_last_table(tmp_path: Path):
    path = tmp_path / "tokens.jsonl"
    old = add_token(path, "a.")
    table = TokenFile(path)
    new = add_token(path, "a.")  # rotation: the new token first ...
    assert table.grant(new) is not None and table.grant(old) is not None
    lines = path.read_text().splitlines()
    path.write_text(lines[1] + "\n")  # ... then the old one's line goes
    assert table.grant(old) is None and table.grant(new) is not None
    path.write_text("{broken\n")  # a half-written file: the last good table stays
    assert table.grant(new) is not None


def test_binding_beyond_loopback_needs_tokens_or_insecure(tmp_path: Path):
    for host in ("127.0.0.1", "::1", "localhost"):
        assert Settings(host=host).host == host
    with pytest.raises(ValidationError, match=r"host 0\.0\.0\.0: beyond loopback without --auth-tokens"):
        Settings(host="0.0.0.0")
    assert Settings(host="0.0.0.0", insecure=True).insecure
    path = tmp_path / "tokens.jsonl"
    add_token(path, "a.")
    # (zenoh off: with tokens, zenoh needs its own guard, tests/test_zenoh_guard.py)
    assert Settings(host="0.0.0.0", auth_tokens=path, zenoh_enabled=False).auth_tokens == path
    path.write_text("{broken\n")
    with pytest.raises(ValidationError, match=r"tokens\.jsonl:1"):
        Settings(auth_tokens=path)


def test_the_cli_prints_a_token_the_server_accepts(tmp_path: Path):
    path = tmp_path / "tokens.jsonl"
    cmd = [sys.executable, "-m", "phim", "auth", "add-token", "--file", str(path), "--prefix", "fleet-a."]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout.strip()
    assert out.startswith("phim_") and out not in path.read_text()
    assert TokenFile(path).grant(out).prefix == "fleet-a."
    bad = subprocess.run(cmd[:-2], capture_output=True, text=True)
    assert bad.returncode == 2 and "--prefix" in bad.stderr


def _post(url: str, stream: str, seq: int, points: np.ndarray, token: str | None) -> httpx.Response:
    from contract import MSGPACK, encode_sector

    headers = {"Content-Type": MSGPACK} | ({"Authorization": f"Bearer {token}"} if token else {})
    body = encode_sector(sector_msg(stream, seq, points))
    return httpx.post(f"{url}/v1/streams/{stream}/sectors", content=body, headers=headers, timeout=60)


def _code(r: httpx.Response) -> str:
    return decode_response(r.content).code.value


def test_a_server_with_tokens(tmp_path: Path):
    path = tmp_path / "tokens.jsonl"
    a, b, admin = add_token(path, "fleet-a."), add_token(path, "fleet-b."), add_token(path, "", admin=True)
    points = sectors()
    with serve(default_detector(), auth_tokens=path) as s:
        bearer = lambda t: {"Authorization": f"Bearer {t}"}  # noqa: E731
        assert httpx.get(f"{s.url}/health/ready").status_code == 200  # health stays open
        # no token, an unknown token: 401 before anything else, naming no stream
        r = _post(s.url, "fleet-a.car", 0, points[0], None)
        assert r.status_code == 401 and r.headers["WWW-Authenticate"].startswith("Bearer")
        err = decode_response(r.content)
        assert err.code is ErrorCode.UNAUTHORIZED and err.field == "Authorization" and err.stream_id is None
        assert _post(s.url, "fleet-a.car", 0, points[0], "phim_unknown").status_code == 401
        for path_ in ("/v1/model", "/v1/streams", "/v1/streams/fleet-a.car", "/metrics"):
            assert httpx.get(f"{s.url}{path_}").status_code == 401, path_
        # a stream outside the token's prefix: 403, also where the stream does not exist (nothing leaks)
        r = _post(s.url, "fleet-b.car", 0, points[0], a)
        assert r.status_code == 403 and _code(r) == "forbidden"
        assert httpx.get(f"{s.url}/v1/streams/fleet-b.nobody", headers=bearer(a)).status_code == 403
        assert httpx.delete(f"{s.url}/v1/streams/fleet-b.car", headers=bearer(a)).status_code == 403
        assert httpx.get(f"{s.url}/v1/streams/fleet-a.nobody", headers=bearer(a)).status_code == 404
        # inside: detections; each token lists its own streams, the admin token all
        for seq in range(2):
            assert _post(s.url, "fleet-a.car", seq, points[seq], a).status_code == 200
            assert _post(s.url, "fleet-b.car", seq, points[seq], b).status_code == 200
        listed = {t: httpx.get(f"{s.url}/v1/streams", headers=bearer(t)).json() for t in (a, admin)}
        assert [x["stream_id"] for x in listed[a]["streams"]] == ["fleet-a.car"]
        assert sorted(x["stream_id"] for x in listed[admin]["streams"]) == ["fleet-a.car", "fleet-b.car"]
        assert httpx.get(f"{s.url}/metrics", headers=bearer(b)).status_code == 200
        # rotation: a new token works at once, the removed one no longer
        new = add_token(path, "fleet-a.")
        path.write_text("".join(line + "\n" for line in path.read_text().splitlines()[1:]))
        assert _post(s.url, "fleet-a.car", 2, points[2], a).status_code == 401
        assert _post(s.url, "fleet-a.car", 2, points[2], new).status_code == 200
        # the clients carry a token (PHIM_TOKEN / --token in the CLI)
        with make_client(ConnectConfig(url=s.url, token=new)) as client:
            assert client.send(sector_msg("fleet-a.car", 3, points[3])).context_sectors == 4
            assert client.model_info()["config"] == "tiny"
        with make_client(ConnectConfig(url=s.url)) as client, pytest.raises(ServerError) as e:
            client.model_info()
        assert e.value.code is ErrorCode.UNAUTHORIZED
        # the load tester: --token, and --stream-prefix inside the token's namespace
        run = [sys.executable, "-m", "phim", "loadtest", "--url", s.url, "--token", new, "--synthetic"]
        run += ["--mode", "closed", "--vehicles", "1", "--duration", "1", "--warmup", "0", "--no-progress"]
        run += ["--max-error-rate", "0"]
        inside = subprocess.run([*run, "--stream-prefix", "fleet-a.lt"], capture_output=True, text=True)
        assert inside.returncode == 0, inside.stdout[-2000:] + inside.stderr[-2000:]
        # streams loadtest-...: not its own; exit code 1 with no threshold given (nothing was measured)
        outside = subprocess.run(run[:-2], capture_output=True, text=True)
        assert outside.returncode == 1 and "refused for their token" in outside.stdout, outside.stdout[-2000:]
    with serve(default_detector(), auth_tokens=path, public_metrics=True) as s:
        assert httpx.get(f"{s.url}/metrics").status_code == 200
        assert httpx.get(f"{s.url}/v1/model").status_code == 401


HUGE_NUMBER = json.dumps({"sha256": "0" * 64, "prefix": "a."})[:-1] + ', "admin": ' + "1" * 5000 + "}"
DEEP = "[" * 100_000 + "]" * 100_000


@pytest.mark.parametrize("line", [HUGE_NUMBER, DEEP], ids=["5000-digit number", "nested 100,000 deep"])
def test_a_line_no_json_parser_takes_keeps_the_last_table_and_logs_once(tmp_path, caplog, line):
    """Before: the parser's ValueError (integer over 4,300 digits) or RecursionError escaped, so every
    authenticated request answered 500. Now the file is refused like any bad file, the line named."""
    with pytest.raises(TokenFileError, match=r"f\.jsonl:1: "):
        parse_tokens(line, "f.jsonl")
    path = tmp_path / "tokens.jsonl"
    token = add_token(path, "a.")
    table = TokenFile(path)
    path.write_text(path.read_text() + line + "\n")
    with caplog.at_level("ERROR", logger="server.auth"):
        assert all(table.grant(token) is not None for _ in range(5))  # the last good table
    assert [r.levelname for r in caplog.records] == ["ERROR"]  # once, not once per request
    assert "tokens.jsonl:2" in caplog.records[0].getMessage()


def test_deleting_the_token_file_revokes_every_token_until_it_is_back(tmp_path, caplog):
    """Before: the deleted file's tokens kept working, and every request logged an ERROR. Fail closed."""
    path = tmp_path / "tokens.jsonl"
    token = add_token(path, "a.")
    table = TokenFile(path)
    saved = path.read_text()
    path.unlink()
    with caplog.at_level("ERROR", logger="server.auth"):
        assert all(table.grant(token) is None for _ in range(5))
    assert len(caplog.records) == 1 and "every token is refused" in caplog.records[0].getMessage()
    assert table.tenant_of("a.car") == "a."  # streams still have a tenant: by their ID
    path.write_text(saved)
    assert table.grant(token) is not None  # back: read again


def test_the_api_description_two_authorization_headers_and_the_token_file_over_http(tmp_path: Path):
    """With tokens, /openapi.json needs one like every route but /health (before: open, with /docs and
    /redoc); two Authorization headers are refused (before: the first one counted); a bad token file keeps
    the last table (before: 500 for every authenticated request) and a deleted one refuses every token."""
    path = tmp_path / "tokens.jsonl"
    a = add_token(path, "fleet-a.")
    points = sectors()
    with serve(default_detector(), auth_tokens=path) as s:
        assert httpx.get(f"{s.url}/openapi.json").status_code == 401
        doc = httpx.get(f"{s.url}/openapi.json", headers={"Authorization": f"Bearer {a}"})
        assert doc.status_code == 200 and "/v1/streams/{stream_id}/sectors" in doc.json()["paths"]
        assert [httpx.get(f"{s.url}/{p}").status_code for p in ("docs", "redoc")] == [404, 404]
        twice = [("Authorization", f"Bearer {a}"), ("Authorization", "Bearer phim_other")]
        r = httpx.get(f"{s.url}/v1/model", headers=twice)
        assert r.status_code == 401 and "2 headers; expected exactly one" in r.json()["message"]
        assert _post(s.url, "fleet-a.car", 0, points[0], a).status_code == 200
        path.write_text(path.read_text() + HUGE_NUMBER + "\n")
        assert _post(s.url, "fleet-a.car", 1, points[1], a).status_code == 200  # the last good table
        path.unlink()
        r = _post(s.url, "fleet-a.car", 2, points[2], a)
        assert r.status_code == 401 and _code(r) == "unauthorized"
    with serve(default_detector()) as s:  # without tokens the description is open, as FastAPI serves it
        assert httpx.get(f"{s.url}/openapi.json").status_code == 200
        assert httpx.get(f"{s.url}/docs").status_code == 200
