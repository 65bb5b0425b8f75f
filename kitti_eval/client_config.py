"""The client's token and configuration: the folder it keeps its files in (:func:`config_dir`), the tokens
``kitti-eval login`` saves there for each service, which token a request sends (:func:`token_for`), and where a
token may go over plain http (:func:`refuse_plain_http`). The standard library only: ``kitti-eval validate``
reads a saved token without the client extra."""

from __future__ import annotations

import json
import os
from pathlib import Path

from .errors import ConfigError

__all__ = [
    "TOKEN_ENV",
    "CONFIG_ENV",
    "ALLOW_HTTP_ENV",
    "config_dir",
    "service_key",
    "saved_token",
    "save_token",
    "saved_services",
    "token_for",
    "refuse_plain_http",
]

#: the environment variable holding the token
TOKEN_ENV = "KITTI_EVAL_TOKEN"
#: the folder of the client's configuration instead of the user's config folder
CONFIG_ENV = "KITTI_EVAL_CONFIG_DIR"
#: ``1``: a token may be sent over plain http to a host other than loopback
ALLOW_HTTP_ENV = "KITTI_EVAL_ALLOW_HTTP"
_TOKENS_FILE = "services.json"


def config_dir() -> Path:
    """The client's folder: ``$KITTI_EVAL_CONFIG_DIR``, else the user's config folder's ``kitti-eval``
    (``$XDG_CONFIG_HOME/kitti-eval``, else ``~/.config/kitti-eval``); a :class:`~kitti_eval.errors.ConfigError`
    naming the settings where there is neither (no ``HOME``, as under ``env -i``, and no home for the uid)."""
    env = os.environ.get(CONFIG_ENV, "").strip()
    if env:
        return Path(env)
    try:
        from platformdirs import user_config_dir
    except ImportError:
        raise ConfigError("the client needs platformdirs: pip install 'kitti-eval[client]'") from None
    try:
        found: Path | None = Path(user_config_dir("kitti-eval", appauthor=False))
    except RuntimeError:  # platformdirs, where ~ cannot be expanded
        found = None
    if found is None or not found.is_absolute():
        raise ConfigError(
            f"the client has no folder for its saved tokens: HOME is not set and the user has no home folder; "
            f"set {CONFIG_ENV} to a folder it may write (or XDG_CONFIG_HOME, or HOME)"
        )
    return found


def service_key(service: str) -> str:
    """A service's address as the saved tokens and keys name it (no trailing slash)."""
    return service.strip().rstrip("/")


def _saved() -> dict[str, str]:
    path = config_dir() / _TOKENS_FILE
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as e:
        raise ConfigError(f"{path}: not the tokens kitti-eval login writes: {e}") from None
    if not isinstance(data, dict) or not all(isinstance(v, str) for v in data.values()):
        raise ConfigError(f"{path}: not the tokens kitti-eval login writes")
    return data


def saved_token(service: str) -> str | None:
    """The token ``kitti-eval login`` saved for ``service``, if any."""
    return _saved().get(service_key(service))


def save_token(service: str, token: str) -> Path:
    """Saves ``token`` for ``service`` in the client's folder (readable by its owner only, written through a
    temporary file of its own: :mod:`kitti_eval.client_state`); returns the file."""
    from .client_state import write_private_json

    tokens = {**_saved(), service_key(service): token}
    return write_private_json(config_dir() / _TOKENS_FILE, tokens)


def saved_services() -> list[str]:
    """The services ``kitti-eval login`` saved a token for."""
    return sorted(_saved())


def token_for(service: str, token: str | None = None) -> str | None:
    """The token to send: ``token``, else ``$KITTI_EVAL_TOKEN``, else the one saved for ``service``."""
    return token or os.environ.get(TOKEN_ENV, "").strip() or saved_token(service)


def _loopback(host: str) -> bool:
    import ipaddress

    if host.lower() in ("localhost", "localhost."):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def refuse_plain_http(service: str, allow_http: bool | None) -> None:
    """The token goes over plain http to a loopback host only, unless the caller says the network is trusted."""
    from urllib.parse import urlsplit

    if allow_http is None:
        allow_http = os.environ.get(ALLOW_HTTP_ENV, "").strip() == "1"
    parts = urlsplit(service)
    if parts.scheme != "http" or allow_http or _loopback(parts.hostname or ""):
        return
    raise ConfigError(
        f"--service {service}: the token would be sent unencrypted (plain http to a host other than this "
        f"machine); use https://, or say the network is trusted with --allow-http (or {ALLOW_HTTP_ENV}=1)"
    )
