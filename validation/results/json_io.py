"""results.json, both ways: a :class:`~.run.Results` as the JSON object the
schema (``schema.json`` beside this file, JSON Schema 2020-12) describes,
and back.

``version`` (major) changes when a field changes meaning, and readers refuse
other majors; ``minor_version`` counts fields added since (run.py lists
them). JSON has no NaN or infinity: a non-finite number (an exact
estimator's slope, an unbounded interval, the mean of a broken render) is
written as null and read back as NaN.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import types
import typing

from mcillum import files
from mcillum.errors import UserError

from . import layout
from .cases import CaseResult, CaseRow, SweepRow
from .run import SCHEMA, VERSION, Results

SCHEMA_FILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "schema.json")


def to_json(record) -> dict:
    """A record as the JSON object results.json holds (see the schema)."""
    out = _encode(record)
    if isinstance(record, Results):
        out["passed"] = record.passed
    return out


def _encode(value):
    if dataclasses.is_dataclass(value):
        out = {}
        for f in dataclasses.fields(value):
            item = getattr(value, f.name)
            if item is None and f.metadata.get("omit_none"):
                continue
            if f.metadata.get("flatten"):
                if item is not None:
                    out.update(_encode(item))
                continue
            out[f.name] = _encode(item)
        return out
    if isinstance(value, dict):
        return {str(k): _encode(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_encode(v) for v in value]
    if hasattr(value, "item"):              # numpy scalars
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None                         # (JSON has no NaN or infinity)
    return value


def _decode(hint, data):
    """``data`` (from JSON) as the type ``hint`` describes."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        empty = data == {} and dataclasses.is_dataclass(args[0])   # (older files)
        return None if data is None or empty else _decode(args[0], data)
    if hint is float and data is None:
        return math.nan                     # written as null (see the module doc)
    if isinstance(hint, type) and issubclass(hint, tuple) and hasattr(hint, "_fields"):
        return hint(*(math.nan if v is None else v for v in data))   # an Interval
    if dataclasses.is_dataclass(hint):
        return from_json(hint, data)
    if origin is list:
        (item,) = typing.get_args(hint) or (typing.Any,)
        return [_decode(item, v) for v in data]
    if origin is dict:
        _, item = typing.get_args(hint) or (str, typing.Any)
        return {k: _decode(item, v) for k, v in data.items()}
    return data


def from_json(cls, data: dict):
    """A record of dataclass ``cls`` from its JSON object (inverse of
    :func:`to_json`); unknown keys are ignored, missing ones raise KeyError."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        if f.metadata.get("flatten"):
            inner = [a for a in typing.get_args(hint) if a is not type(None)][0]
            required = [g.name for g in dataclasses.fields(inner)
                        if g.default is dataclasses.MISSING
                        and g.default_factory is dataclasses.MISSING]
            kwargs[f.name] = from_json(inner, data) if all(k in data for k in required) \
                else None
        elif f.name in data:
            kwargs[f.name] = _decode(hint, data[f.name])
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise KeyError(f.name)
    record = cls(**kwargs)
    if cls is CaseResult:                   # rows of a sweep or of a case
        row = SweepRow if record.sweep is not None else CaseRow
        record.estimators = [from_json(row, r) for r in data["estimators"]]
    return record



class ResultsError(UserError, ValueError):
    """results.json is unreadable, of another version, or incomplete."""


class NoResultsError(ResultsError, FileNotFoundError):
    """The directory holds no results.json (the command line names no run)."""

    usage = True



def load(run_dir: str) -> Results:
    """The :class:`Results` of ``run_dir/results.json``; :class:`ResultsError`
    says what is wrong with it and what to do."""
    path = layout.results_json(run_dir)
    again = f"run `mcillum validate --out {run_dir}` again"
    if not os.path.isfile(path):
        raise NoResultsError(f"no results.json in {run_dir}: run `mcillum validate "
                             f"--out {run_dir}` first")
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except (ValueError, UnicodeDecodeError) as err:
        raise ResultsError(f"{path} is not valid JSON ({err}): {again}") from None
    if not isinstance(data, dict) or data.get("schema") != SCHEMA:
        raise ResultsError(f"{path} is not an mcillum results file (no \"schema\": "
                           f"\"{SCHEMA}\")")
    if data.get("version") != VERSION:
        raise ResultsError(f"{path} has results version {data.get('version')!r}; this "
                           f"mcillum reads version {VERSION}: {again}")
    try:
        record = from_json(Results, data)
        record.minor_version = data.get("minor_version", 0)
        return record
    except KeyError as err:
        raise ResultsError(f"{path} lacks the field {err}: {again}") from None



def write_json(path: str, results: Results) -> None:
    files.write_text(path, json.dumps(to_json(results), indent=2, allow_nan=False,
                                      default=float) + "\n")
