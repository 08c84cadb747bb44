"""API keys and who owns what.

Three set-ups (docs/service.md, "Keys"):
- no keys (default): every caller may use every model, as on a private machine;
- `PHD_API_KEY` alone: one key, and its holder is the admin (sees and deletes everything);
- `PHD_KEYS_FILE`: a JSON object {"name": "key", ...} of named keys. Each name owns the
  models it uploads and the jobs it submits, and sees and deletes only those: another
  name's model answers 404, as if it did not exist. `PHD_API_KEY`, if also set, is the
  admin key that sees all.
Keys are compared in constant time (hmac.compare_digest) against every configured key.
"""

from __future__ import annotations

import hmac
import json
from dataclasses import dataclass
from pathlib import Path

ADMIN = "admin"


@dataclass(frozen=True)
class Principal:
    """Who is calling: a key's name, and whether it sees everything."""

    name: str | None
    admin: bool

    def may_see(self, owner: str | None) -> bool:
        return self.admin or owner == self.name


OPEN = Principal(None, True)      # no keys configured


class KeyRing:
    def __init__(self, admin_key: str | None, keys_file: Path | None):
        self.keys: list[tuple[bytes, Principal]] = []
        if keys_file is not None:
            self.keys += [(key.encode(), Principal(name, False)) for name, key in read_keys(keys_file).items()]
        if admin_key is not None:
            self.keys.append((admin_key.encode(), Principal(ADMIN, True)))

    @property
    def required(self) -> bool:
        return bool(self.keys)

    def identify(self, header: str | None) -> Principal | None:
        """The caller of an 'Authorization: Bearer <key>' header; None for a missing or wrong key."""
        if not self.keys:
            return OPEN
        if header is None:
            return None
        scheme, _, token = header.partition(" ")
        token_bytes = token.strip().encode("latin-1", "replace")
        found = None
        for key, principal in self.keys:   # every key compared: the time does not tell which matched
            if hmac.compare_digest(token_bytes, key) and scheme.lower() == "bearer":
                found = principal
        return found


def read_keys(path: Path) -> dict[str, str]:
    """{"name": "key"} from a JSON file: names and keys non-empty strings, keys distinct."""
    try:
        keys = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"PHD_KEYS_FILE {path}: cannot read it as JSON ({exc})") from None
    if not isinstance(keys, dict) or not keys or not all(
            isinstance(k, str) and k and isinstance(v, str) and len(v) >= 8 for k, v in keys.items()):
        raise ValueError(f"PHD_KEYS_FILE {path}: expected a JSON object of name -> key (keys of 8 or more characters)")
    if len(set(keys.values())) != len(keys):
        raise ValueError(f"PHD_KEYS_FILE {path}: two names share a key")
    if ADMIN in keys:
        raise ValueError(f"PHD_KEYS_FILE {path}: the name '{ADMIN}' is reserved for PHD_API_KEY")
    return keys
