"""The base of every parameter model: :class:`StrictModel` and the field
metadata that names a field's command-line option (:func:`option`).

A module of its own, importing nothing of tiledsm, so that the stages'
parameter models (:class:`tiledsm.match.params.SGVLLParams`...) and the
recipe sections that hold them (:mod:`tiledsm.recipes`) share one base
without an import circle.
"""

from __future__ import annotations

from typing import Any, Callable, Iterable

from pydantic import BaseModel, ConfigDict, ValidationInfo

__all__ = ["StrictModel", "option", "not_below", "registered"]


def option(name: str | None) -> dict[str, str | None]:
    """A field's command-line spelling, for ``Field(json_schema_extra=...)``:
    the spec is the one place that says which option sets a field, and
    errors found validating a command's options name that option
    (:func:`tiledsm.recipes.options_of`, :func:`tiledsm.cli.run.recipe_of_options`).
    ``None``: a section no option of the recipe's command sets (its
    model's options are another command's: ``orient:`` of a DSM recipe)."""
    return {"option": name}


def not_below(other: str) -> Callable[[Any, ValidationInfo], Any]:
    """A field validator (``field_validator("P2")(not_below("P1"))``): the
    value is at least that of field ``other``, declared before it. Give the
    field ``validate_default=True`` so a default is checked against an
    ``other`` given alone."""
    def check(value: Any, info: ValidationInfo) -> Any:
        if other in info.data and value < info.data[other]:
            raise ValueError(f"must be >= {other} ({info.data[other]}), got {value}")
        return value

    return check


def registered(registry: Callable[[], Iterable[str]], what: str) -> Callable[[str], str]:
    """A field validator (``field_validator("kernel")(registered(lambda: KERNELS,
    "matching kernel"))``): the value is a name of ``registry()`` (called
    at validation: a registry filled by imports, or imported only then);
    the message names the value and the known names."""
    def check(value: str) -> str:
        known = sorted(registry())
        if value not in known:
            raise ValueError(f"unknown {what} {value!r}; known: {', '.join(known)}")
        return value

    return check


class StrictModel(BaseModel):
    """Base of every recipe and parameter model: unknown fields are errors,
    values frozen (so hashable, when every field is).

    A model is a dask task's argument (the DSM's parameters go to every
    matching task): :meth:`__dask_tokenize__` makes its token the same for
    equal values in any process (dask's fallback for an unknown object is
    not: two equal models would get two tokens)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    def __dask_tokenize__(self) -> tuple[str, str]:
        return f"{type(self).__module__}.{type(self).__qualname__}", self.model_dump_json()
