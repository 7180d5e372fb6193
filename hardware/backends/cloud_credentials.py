"""Credentials for FarmBot's web app: a token or an email and a password, from the
environment or a token file outside any git work tree.

They are kept in memory only: never in a repr, a message, a log, a file or scan.json
(`CloudCredentials.secrets` gives the cloud backend what to scrub from error messages).
"""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Mapping
from pathlib import Path

import flowerpose
from flowerpose.errors import InputError

DEFAULT_SERVER = "https://my.farm.bot"
ENV_TOKEN, ENV_EMAIL, ENV_PASSWORD, ENV_SERVER = ("FARMBOT_TOKEN", "FARMBOT_EMAIL",
                                                  "FARMBOT_PASSWORD", "FARMBOT_SERVER")
#: This project's own checkout (a token file is refused inside it even without a .git).
_REPOSITORY = Path(flowerpose.__file__).resolve().parents[1]


class CloudCredentials:
    """How to log in to FarmBot's web app: a token, or an email and a password.

    The secrets stay in this object's private attributes: its repr names only the server and
    the kind of credential.
    """

    def __init__(self, *, token: dict | None = None, email: str | None = None,
                 password: str | None = None, server: str = DEFAULT_SERVER):
        if token is None and not (email and password):
            raise InputError(f"{ENV_EMAIL} and {ENV_PASSWORD}", "FarmBot login needs a token "
                             "or both an email and a password")
        self._token, self._email, self._password = token, email, password
        self.server = server.rstrip("/")

    @property
    def kind(self) -> str:
        return "token" if self._token is not None else "email and password"

    def __repr__(self) -> str:
        return f"CloudCredentials(server={self.server!r}, {self.kind})"

    @classmethod
    def from_environment(cls, environ: Mapping[str, str] | None = None,
                         token_file: str | Path | None = None) -> CloudCredentials:
        """Credentials from `token_file` (which must lie outside any git work tree), else
        FARMBOT_TOKEN, else FARMBOT_EMAIL and FARMBOT_PASSWORD (FARMBOT_SERVER, default
        https://my.farm.bot). A token is the JSON that FarmBot's /api/tokens returns or its
        encoded part (a JWT). InputError, one line and no secret, when none is usable."""
        environ = os.environ if environ is None else environ
        server = _checked_server(environ.get(ENV_SERVER) or DEFAULT_SERVER)
        if token_file is not None:
            return cls(token=_read_token_file(Path(token_file)), server=server)
        if environ.get(ENV_TOKEN):
            return cls(token=parse_token(environ[ENV_TOKEN], ENV_TOKEN), server=server)
        email, password = environ.get(ENV_EMAIL), environ.get(ENV_PASSWORD)
        if email and password:
            return cls(email=email, password=password, server=server)
        missing = ENV_PASSWORD if email else ENV_EMAIL if password else ENV_TOKEN
        raise InputError(missing, f"not set: the FarmBot cloud needs {ENV_TOKEN}, or "
                         f"{ENV_EMAIL} and {ENV_PASSWORD} (with {ENV_SERVER} for another "
                         "server), in the environment, or a token file outside the repository")

    def secrets(self) -> list[str]:
        """The strings that must never be shown: to scrub from messages."""
        token = (self._token or {}).get("token", {})
        values = [self._password, self._email, token.get("encoded"),
                  (token.get("unencoded") or {}).get("sub")]
        return [v for v in values if isinstance(v, str) and len(v) >= 4]


def parse_token(text: str, source: str) -> dict:
    """A FarmBot token, {"token": {"unencoded": {...}, "encoded": "<jwt>"}}, from the JSON
    that /api/tokens returns (with or without its outer "token"), or from the JWT alone (its
    payload is the unencoded part). InputError naming `source`, never the token, otherwise."""
    text = text.strip()
    problem = ("not a FarmBot token: expected the JSON that FarmBot's /api/tokens returns, "
               "or its encoded part")
    try:
        if text.startswith("{"):
            data = json.loads(text)
            token = data.get("token", data)
            unencoded, encoded = token["unencoded"], token["encoded"]
        else:
            import jwt

            # Only read: the claims name the bot and its broker; FarmBot's server checks
            # the signature when the token is used.
            try:
                unencoded = jwt.decode(text, options={"verify_signature": False})
            except jwt.PyJWTError:
                raise InputError(source, problem) from None
            encoded = text
    except (ValueError, KeyError, IndexError, TypeError, AttributeError):
        raise InputError(source, problem) from None
    if not (isinstance(unencoded, dict) and isinstance(encoded, str)
            and all(isinstance(unencoded.get(k), str) for k in ("bot", "mqtt", "iss"))):
        raise InputError(source, problem + " (it names no bot, mqtt and iss)")
    return {"token": {"unencoded": unencoded, "encoded": encoded}}


def git_work_tree(path: Path) -> Path | None:
    """The git work tree (or this repository) that holds `path`, None when none does."""
    path = path.resolve()
    for folder in path.parents:
        if (folder / ".git").exists():
            return folder
    return _REPOSITORY if path.is_relative_to(_REPOSITORY) else None


def _read_token_file(path: Path) -> dict:
    """The token in `path`, which must lie outside any git work tree, so it can never be
    committed, and be readable by its owner alone: a file others may read is refused
    before it is read."""
    tree = git_work_tree(path)
    if tree is not None:
        raise InputError(path, f"a token file must lie outside the git work tree {tree}, so "
                         "it can never be committed; move it (e.g. to ~/.config/farmbot/)")
    try:
        mode = path.stat().st_mode
        if mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise InputError(path, "other users may read this token file; chmod 600 it, then "
                             "run again")
        text = path.read_text()
    except FileNotFoundError:
        raise InputError(path, "token file not found") from None
    except OSError as err:
        raise InputError(path, f"cannot read the token file ({err.strerror})") from None
    return parse_token(text, str(path))


#: Hosts an http:// server may be on: this machine (a self-hosted server for development).
_LOCAL_HOSTS = ("localhost", "127.0.0.1", "::1")


def _checked_server(server: str) -> str:
    """FARMBOT_SERVER, refused when it would send a password or token unencrypted."""
    from urllib.parse import urlparse

    address = urlparse(server)
    if address.scheme not in ("https", "http") or not address.hostname:
        raise InputError(ENV_SERVER, f"expected https://host, got {server!r}")
    if address.scheme == "http" and address.hostname not in _LOCAL_HOSTS:
        raise InputError(ENV_SERVER, f"{server} is http://: the login would cross the network "
                         "unencrypted; use https:// (http:// only for a server on this machine)")
    return server
