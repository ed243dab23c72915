"""How every settings dataclass rejects a value: one error type whose message starts with the setting's name
(the config prefixes its section, e.g. ``train.max_steps=0 is not allowed; expected a positive integer``)."""

from __future__ import annotations


class SettingError(ValueError):
    """A setting whose value is not allowed; the message starts with the setting's name."""


def require(ok: bool, name: str, value: object, allowed: str) -> None:
    if not ok:
        raise SettingError(f"{name}={value!r} is not allowed; expected {allowed}")
