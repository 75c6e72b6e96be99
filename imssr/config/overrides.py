"""Values merged onto a config: ``section.field=value`` overrides (``--set``), the fields of a
JSON object (:meth:`RunConfig.from_dict <imssr.config.RunConfig.from_dict>`) and ``--logger``.

Types go through OmegaConf structured configs: OmegaConf holds the dataclasses' schema and
rejects unknown keys and values it cannot convert to a field's type.  imssr adds what OmegaConf
allows and a run must not: NaN and infinity.  The text of string fields never reaches OmegaConf
(:func:`_set_aside_text`).
"""
from __future__ import annotations

import copy
import json
import math
from dataclasses import fields
from typing import Any, TypeVar

from omegaconf import OmegaConf
from omegaconf.errors import ConfigKeyError, ValidationError

from imssr.config.schema import FIELD_TYPES, SECTIONS
from imssr.errors import ImssrError
from imssr.settings import Sections, type_phrase

RunConfig = TypeVar("RunConfig", bound=Sections)
"""A run's config, :class:`imssr.config.RunConfig` (which reads and merges through this module)."""

def _merged(cfg: RunConfig, data: dict[str, Any], raw: dict[str, str]) -> RunConfig:
    """``cfg`` with the (nested) ``data`` merged on by OmegaConf; ``raw`` maps an override's
    dotted key to its text, for errors that quote what was typed.  Text is taken as it is
    (:func:`_set_aside_text`)."""
    base, data, texts = _set_aside_text(cfg, data, raw)
    try:
        merged = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(base), data))
    except ConfigKeyError as exc:  # also ConfigAttributeError
        section, _, name = str(exc.full_key).partition(".")
        if not name:
            raise ImssrError(f"unknown config section {section!r}") from None
        raise ImssrError(f"unknown setting {exc.full_key!r}; {section} has: "
                         f"{', '.join(sorted(f.name for f in fields(SECTIONS[section])))}") from None
    except (ValidationError, OverflowError) as exc:
        # OverflowError: an integer too large for a float field (no key attached).
        key = getattr(exc, "full_key", None) or _overflowing(data)
        value = getattr(exc, "value", None)
        if isinstance(exc, OverflowError) and key not in raw:
            raise ImssrError(f"{key} must be a finite number, got an integer too large for a float") from None
        if key in raw:
            raise ImssrError(f"{key} expects {_expected(key)}, got {raw[key]!r}") from None
        raise ImssrError(f"{key} must be {type_phrase(FIELD_TYPES.get(key, str))}, got {value!r}") from None
    for key, text in texts.items():
        set_field(merged, key, text)
    for key, text in raw.items():
        if FIELD_TYPES[key] is float and not _is_finite(_get(merged, key)):
            raise ImssrError(f"{key} expects a finite number, got {text!r}")
    return merged


def _set_aside_text(cfg: RunConfig, data: dict[str, Any], raw: dict[str, str]
                    ) -> tuple[RunConfig, dict[str, Any], dict[str, str]]:
    """``cfg`` and ``data`` with the text of their string fields taken out, and that text by
    dotted key, to be put back after the merge.

    Config values are data: OmegaConf reads ``${...}`` in a value as an interpolation (``${oc.env:
    NAME}`` would copy an environment variable, a secret, into config.json and the checkpoint) and
    ``???`` as "missing".  A string field needs no conversion, so its text never reaches OmegaConf
    and stays as written; such text in a field of another type is refused."""
    texts: dict[str, str] = {}
    base = copy.deepcopy(cfg)
    for key in FIELD_TYPES:
        if not _text_of(key, _get(cfg, key), {}, texts):
            set_field(base, key, "")
    rest: dict[str, Any] = {}
    for name, value in data.items():
        if name in SECTIONS and isinstance(value, dict):
            rest[name] = {}
            for field_name, item in value.items():
                if _text_of(f"{name}.{field_name}", item, raw, texts):
                    rest[name][field_name] = item
        elif _text_of(name, value, raw, texts):
            rest[name] = value
    return base, rest, texts


def _text_of(key: str, value: Any, raw: dict[str, str], texts: dict[str, str]) -> bool:
    """Whether ``value`` of ``key`` goes to OmegaConf; the text of a string field goes into
    ``texts`` instead.  Text that OmegaConf would interpret is refused for other fields."""
    kind = FIELD_TYPES.get(key)
    if isinstance(value, str) and kind is str:
        texts[key] = value
        return False
    if kind is str:
        # Another value for a string field (``"device": 5``) is converted or refused by
        # OmegaConf, and the field's rules judge what it became: the base's text must not be
        # put back over it.
        texts.pop(key, None)
        return True
    if isinstance(value, str) and kind is not None and _interpolated(value):
        raise ImssrError(f"{key} expects {_expected(key)}, got {raw.get(key, value)!r}")
    return True


def _interpolated(text: str) -> bool:
    """Whether OmegaConf would read ``text`` as something other than itself."""
    return "${" in text or text == "???"


def _expected(key: str) -> str:
    kind = FIELD_TYPES.get(key, str)
    return "a finite number" if kind is float else type_phrase(kind)


def _overflowing(data: dict[str, Any]) -> str:
    """The first ``section.field`` of ``data`` that holds an integer too large for a float
    (OmegaConf's OverflowError names none)."""
    for section, values in data.items():
        for name, value in (values.items() if isinstance(values, dict) else ()):
            if isinstance(value, int) and FIELD_TYPES.get(f"{section}.{name}") is float and not _is_finite(value):
                return f"{section}.{name}"
    return "a config value"


def _get(cfg: RunConfig, key: str) -> Any:
    section, _, name = key.rpartition(".")
    return getattr(getattr(cfg, section) if section else cfg, name)


def set_field(cfg: RunConfig, key: str, value: Any) -> None:
    """Set the field ``section.name`` (or a top-level one) of ``cfg`` to ``value`` as it is."""
    section, _, name = key.rpartition(".")
    setattr(getattr(cfg, section) if section else cfg, name, value)


def _is_finite(value) -> bool:
    try:
        return math.isfinite(value)
    except OverflowError:  # an integer too large for a float
        return False


def apply_overrides(cfg: RunConfig, overrides: list[str]) -> RunConfig:
    """``cfg`` with ``section.field=value`` strings applied (the CLI's ``--set``).

    A value is converted to its field's type by OmegaConf (``64``, ``1e-3``, ``true``); a
    JSON string (``"a b"``) is unquoted; anything else is the text itself.
    """
    data: dict[str, dict[str, Any]] = {}
    raw: dict[str, str] = {}
    for item in overrides:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise ImssrError(f"override {item!r} must look like section.field=value")
        key, text = item.split("=", 1)
        section, name = key.split(".", 1)
        if section not in SECTIONS:
            raise ImssrError(f"unknown config section {section!r} in override {item!r}")
        data.setdefault(section, {})[name] = _override_value(key, text)
        raw[key] = text
    return _merged(cfg, data, raw)


def _override_value(key: str, text: str) -> Any:
    """What OmegaConf gets for ``key=text``: the text itself, except a JSON string (unquoted)
    and, for an integer field, a JSON number with an integral value (``1e3``, ``64.0``)."""
    try:
        value = json.loads(text)
    except json.JSONDecodeError:
        return text
    if isinstance(value, str):
        return value
    if FIELD_TYPES.get(key) is int and isinstance(value, float) and math.isfinite(value) and value.is_integer():
        return int(value)
    return text


LOGGERS = ("csv", "tensorboard", "wandb")
"""The names ``--logger`` takes; CSV logs are written whatever it says."""


def logger_fields(text: str, no_tensorboard: bool = False) -> dict[str, bool]:
    """``--logger csv,tensorboard,wandb`` as the config fields it sets (``train.tensorboard``,
    ``train.wandb``); ``no_tensorboard``: ``--no-tensorboard`` was given too."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in LOGGERS]
    if unknown:
        raise ImssrError(f"unknown logger {unknown[0]!r} in --logger; choose from {', '.join(LOGGERS)}")
    if no_tensorboard and "tensorboard" in names:
        raise ImssrError("--no-tensorboard and --logger ...tensorboard contradict each other; give one")
    return {"train.tensorboard": "tensorboard" in names, "train.wandb": "wandb" in names}
