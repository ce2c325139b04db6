"""A minimal stand-in for the `omegaconf` package, enough for the official DC-AE config code.

The official `dc_ae_f32c32()` builds its config with
    OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(DCAEConfig), OmegaConf.from_dotlist(...)))
The GPU machine has no omegaconf, so the harness puts this directory first on sys.path. Only the
calls used there are implemented: dotlist parsing (scalars and [a,b,c] lists), merging into a
dataclass, and the "${..name}" parent interpolation the official dataclasses use.
"""
import dataclasses

MISSING = "???"


def _parse_scalar(text):
    low = text.lower()
    if low in ("null", "none"):
        return None
    if low in ("true", "false"):
        return low == "true"
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def _parse_value(text):
    text = text.strip()
    if text.startswith("[") and text.endswith("]"):
        inner = text[1:-1].strip()
        return [] if not inner else [_parse_scalar(t.strip()) for t in inner.split(",")]
    return _parse_scalar(text)


class _Structured:
    def __init__(self, cls, overrides=None):
        self.cls, self.overrides = cls, overrides or {}


def _build(obj, overrides, parent_values):
    cls = type(obj)
    values = {}
    for f in dataclasses.fields(cls):
        values[f.name] = getattr(obj, f.name)
    for key, val in overrides.items():
        if key not in values:
            raise KeyError(f"omegaconf stand-in: unknown key '{key}' for {cls.__name__}")
        if not dataclasses.is_dataclass(values[key]):
            values[key] = list(val) if isinstance(val, list) else val
    for key, val in list(values.items()):
        if isinstance(val, str) and val.startswith("${..") and val.endswith("}"):
            values[key] = parent_values[val[4:-1]]
    for key, val in list(values.items()):
        if dataclasses.is_dataclass(val):
            values[key] = _build(val, overrides.get(key, {}), values)
    return cls(**values)


class OmegaConf:
    @staticmethod
    def from_dotlist(items):
        tree = {}
        for item in items:
            if not item:
                continue
            key, _, value = item.partition("=")
            node = tree
            parts = key.split(".")
            for p in parts[:-1]:
                node = node.setdefault(p, {})
            node[parts[-1]] = _parse_value(value)
        return tree

    @staticmethod
    def structured(cls):
        return _Structured(cls)

    @staticmethod
    def merge(base, overrides):
        return _Structured(base.cls, overrides)

    @staticmethod
    def to_object(structured):
        return _build(structured.cls(), structured.overrides, {})
