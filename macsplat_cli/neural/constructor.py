"""Upstream's model constructor strings, read without evaluating them, and the error every model-configuration
check raises.

An official MASt3R checkpoint stores its architecture as the Python call that built it
(``args.model = "AsymmetricMASt3R(enc_depth=24, ..., depth_mode=('exp', -inf, inf))"``);
:func:`parse_constructor_string` reads it with :func:`ast.parse` and accepts literals only.
:meth:`~.config.BackboneConfig.from_args_string` turns the keywords into a configuration.
"""

from __future__ import annotations

import ast
import math
from typing import Any

from ..errors import InputError

__all__ = ["ModelConfigError", "parse_constructor_string"]


class ModelConfigError(InputError, ValueError):
    """A model configuration (constructor string, ``config.json``, or field values) is invalid or unsupported."""


def parse_constructor_string(s: str) -> tuple[str, dict[str, Any]]:
    """Split ``"Name(k=v, ...)"`` into ``("Name", {k: v})`` without evaluating anything.

    Values may be ``int``/``float``/``str``/``bool``/``None`` literals, ``inf``/``nan`` (bare, or as
    ``np.inf``/``math.inf``/``float('inf')``), unary ``-``/``+`` on those, and tuples/lists of values.
    Positional arguments, ``**kwargs``, duplicate keywords, names, calls, operators and every other
    construct raise :class:`ModelConfigError`.
    """
    if not isinstance(s, str):
        raise ModelConfigError(f"the model constructor string must be a str, got {type(s).__name__}")
    if len(s) > _MAX_CONSTRUCTOR_CHARS:
        raise ModelConfigError(f"the model constructor string is too long ({len(s)} characters)")
    try:
        tree = ast.parse(s.strip(), mode="eval")
    except SyntaxError as e:
        raise ModelConfigError(
            f"the model constructor string is not valid Python syntax: {e.msg} in {s!r:.200}"
        ) from None
    except (ValueError, RecursionError, MemoryError) as e:  # null bytes; nesting too deep for the parser
        raise ModelConfigError(f"the model constructor string cannot be parsed ({type(e).__name__}: {e})") from None
    call = tree.body
    if not isinstance(call, ast.Call) or not isinstance(call.func, ast.Name):
        raise ModelConfigError(f"expected 'ModelName(key=value, ...)', got {s!r}")
    if call.args:
        raise ModelConfigError(f"{call.func.id}(...) has positional arguments; only key=value is supported")
    kwargs: dict[str, Any] = {}
    for kw in call.keywords:
        if kw.arg is None:
            raise ModelConfigError(f"{call.func.id}(...) uses **kwargs; only key=value is supported")
        if kw.arg in kwargs:
            raise ModelConfigError(f"keyword {kw.arg!r} is given twice")
        try:
            kwargs[kw.arg] = _literal(kw.value, kw.arg)
        except RecursionError:
            raise ModelConfigError(f"the value of {kw.arg!r} is nested too deeply") from None
    return call.func.id, kwargs


_MAX_CONSTRUCTOR_CHARS = 100_000  # upstream's strings are ~600 characters


_SPECIAL_FLOATS = {"inf": math.inf, "nan": math.nan}


def _literal(node: ast.expr, key: str) -> Any:
    if isinstance(node, ast.Constant) and isinstance(node.value, (int, float, str, bool, type(None))):
        return node.value
    if isinstance(node, ast.Name) and node.id in _SPECIAL_FLOATS:
        return _SPECIAL_FLOATS[node.id]
    if (
        isinstance(node, ast.Attribute)
        and node.attr in _SPECIAL_FLOATS
        and isinstance(node.value, ast.Name)
        and node.value.id in ("np", "numpy", "math", "torch")
    ):
        return _SPECIAL_FLOATS[node.attr]
    if (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Name)
        and node.func.id == "float"
        and len(node.args) == 1
        and not node.keywords
        and isinstance(node.args[0], ast.Constant)
        and isinstance(node.args[0].value, str)
        and node.args[0].value.strip().lower() in ("inf", "-inf", "+inf", "nan")
    ):
        return float(node.args[0].value)
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        v = _literal(node.operand, key)
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            return -v if isinstance(node.op, ast.USub) else v
    if isinstance(node, (ast.Tuple, ast.List)):
        return tuple(_literal(e, key) for e in node.elts)
    raise ModelConfigError(f"unexpected value for {key!r}: {ast.unparse(node)!r} (only literals are accepted)")
