"""API keys: every request needs one; each key is a tenant that sees only its own rows; revoked keys stop."""

from __future__ import annotations

import uuid

import pytest
from fastapi.testclient import TestClient

from service.auth import KeyVerifier, create_api_key, list_api_keys, revoke_api_key
from service.db.session import get_session_factory, session_scope
from service.settings import Settings


class TestKeys:
    def test_stored_hashed(self, settings: Settings) -> None:
        with session_scope(get_session_factory(settings.database)) as session:
            row, key = create_api_key(session, "bob")
            assert key.startswith(f"pgs_{row.prefix}_")
            assert key not in row.key_hash
            assert len(row.key_hash) == 64
            assert [r.name for r in list_api_keys(session)] == ["bob"]

    def test_verify_and_revoke(self, settings: Settings) -> None:
        verifier = KeyVerifier(ttl_s=0)
        with session_scope(get_session_factory(settings.database)) as session:
            row, key = create_api_key(session, "bob")
            assert verifier.verify(session, key).id == row.id  # type: ignore[union-attr]
            assert verifier.verify(session, key[:-1] + ("A" if key[-1] != "A" else "B")) is None
            assert verifier.verify(session, "pgs_nonsense") is None
            assert revoke_api_key(session, row.prefix) is not None
            assert verifier.verify(session, key) is None
            assert revoke_api_key(session, str(uuid.uuid4())) is None

    @pytest.mark.parametrize("spelling", ["listed", "pgs_prefix", "whole key"])
    def test_revoke_takes_the_prefix_as_a_person_copies_it(self, settings: Settings, spelling: str) -> None:
        with session_scope(get_session_factory(settings.database)) as session:
            row, key = create_api_key(session, "carol")
            ident = {"listed": row.prefix, "pgs_prefix": f"pgs_{row.prefix}", "whole key": key}[spelling]
            revoked = revoke_api_key(session, ident)
            assert revoked is not None
            assert revoked.id == row.id
            assert KeyVerifier(ttl_s=0).verify(session, key) is None


class TestRequests:
    @pytest.mark.parametrize(
        "headers",
        [
            {},
            {"Authorization": "Bearer"},
            {"Authorization": "Basic dXNlcjpwdw=="},
            {"Authorization": "Bearer nope"},
        ],
    )
    def test_missing_or_wrong_key(self, client: TestClient, headers: dict[str, str]) -> None:
        response = client.get("/v1/jobs", headers=headers)
        assert response.status_code == 401
        body = response.json()
        assert body["type"] == "unauthorized"
        assert "API key" in body["message"]
        assert response.headers["www-authenticate"] == "Bearer"

    def test_revoked_key_refused(self, client: TestClient, settings: Settings, auth: dict[str, str]) -> None:
        assert client.get("/v1/jobs", headers=auth).status_code == 200
        prefix = auth["Authorization"].split("_")[1]
        with session_scope(get_session_factory(settings.database)) as session:
            revoke_api_key(session, prefix)
        assert client.get("/v1/jobs", headers=auth).status_code == 401

    def test_health_needs_no_key(self, client: TestClient) -> None:
        assert client.get("/healthz").json() == {"status": "ok", "checks": {}}
        ready = client.get("/readyz")
        assert ready.status_code == 200, ready.text
        assert ready.json()["checks"] == {"database": "ok", "broker": "ok", "storage": "ok"}
