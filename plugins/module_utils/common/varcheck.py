# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
"""The types of the variables a user sets, checked against the roles' argument specs before any
role runs: one line per variable with its value, what it must be and the fix. Ansible's own
validation of a role's arguments would print the whole spec (hundreds of lines per host) and
internal class names instead.
"""

from __future__ import annotations

import json

from ansible.module_utils.common.arg_spec import ArgumentSpecValidator

KINDS = {
    "int": "a whole number",
    "float": "a number",
    "bool": "true or false",
    "str": "a string",
    "path": "a path",
    "list": "a list",
    "dict": "a mapping",
    "raw": "a value",
}
# keys of a spec that say nothing about a value a user has set
_DOCS = ("description", "default", "required", "version_added", "short_description")


def _clean(spec: dict) -> dict:
    out = {k: v for k, v in spec.items() if k not in _DOCS}
    if isinstance(out.get("options"), dict):
        out["options"] = {n: _clean(s) for n, s in out["options"].items()}
    return out


def merged_specs(documents) -> dict:
    """{variable: spec} from argument_specs.yml documents (parsed). A variable of several entry
    points takes the main entry point's spec, with the choices of all of them."""
    merged: dict = {}
    for document in documents:
        entries = (document or {}).get("argument_specs") or {}
        for entry in sorted(entries, key=lambda e: e != "main"):
            for name, spec in ((entries[entry] or {}).get("options") or {}).items():
                if name not in merged:
                    merged[name] = dict(spec)
                elif spec.get("choices") and merged[name].get("choices"):
                    extra = [c for c in spec["choices"] if c not in merged[name]["choices"]]
                    merged[name]["choices"] = list(merged[name]["choices"]) + extra
    return merged


def want(spec: dict) -> str:
    """What a value must be, in a person's words."""
    if spec.get("choices"):
        return "one of " + ", ".join(str(c) for c in spec["choices"])
    kind = KINDS.get(spec.get("type", "str"), spec.get("type", "str"))
    if spec.get("type") == "list" and spec.get("elements"):
        return f"a list of {KINDS.get(spec['elements'], spec['elements'])} items"
    return kind


def show(value) -> str:
    if isinstance(value, str):
        return repr(str(value))
    try:
        return json.dumps(value, default=str)
    except (TypeError, ValueError):
        return repr(value)


def _example(name: str, spec: dict) -> str:
    default = spec.get("default")
    if spec.get("choices"):
        return f"-e {name}={spec['choices'][0]}"
    if spec.get("type") in ("list", "dict"):
        sample = default if default not in (None, "") else ([] if spec["type"] == "list" else {})
        return f"""-e '{json.dumps({name: sample})}'"""
    if default in (None, "", [], {}):
        return ""
    return f"-e {name}={default if isinstance(default, str) else json.dumps(default)}"


def problems(specs: dict, values: dict) -> list[str]:
    """One message per variable in `values` whose value its spec refuses."""
    out = []
    for name in sorted(values):
        if name not in specs:
            continue
        spec = _clean(specs[name])
        # a list of the errors (the result's own error object is always true)
        errors = ArgumentSpecValidator({name: spec}).validate({name: values[name]}).errors.errors
        if not errors:
            continue
        nested = spec.get("options") and spec.get("type") in ("dict", "list")
        detail = f" ({errors[0]})" if nested else ""
        example = _example(name, specs[name])
        out.append(
            f"{name}: {show(values[name])} is not {want(spec)}{detail}. Fix: give {want(spec)}"
            + (f", such as {example}" if example else "")
        )
    return out
