"""Every module's documentation says what it does in check mode and in diff mode, and on which platforms,
and the code agrees; an option that several modules take has one text, from a doc fragment
(plugins/doc_fragments/), unless it is listed below with the reason it differs.

What "the code agrees" means, read from the source with ast (nothing is imported or run):

- check mode: the attribute's support is `none` exactly when Ansible would skip the task in check mode - the
  module's AnsibleModule(...) is made without supports_check_mode=True, or its action plugin (plugins/action/,
  same name) sets _supports_check_mode = False (ActionBase's default is True; a module whose work is all its
  action plugin's has no AnsibleModule, and its action plugin decides alone). Whether the support is `full` or
  `partial` is the module's own word, in its details.
- diff mode: the support is `full` or `partial` exactly when the code can return a `diff` key - a dict literal
  with the key "diff", an assignment to x["diff"], or diff=... given to dict(), .update(), exit_json() or
  fail_json() - in the module, its action plugin, or a file of the collection that either imports, however
  indirectly. That reads more than the module runs: a module that imports a file for other functions than the
  one returning a diff is listed in DIFF_SCAN_MISREADS with the reason, and an entry that the scan no longer
  needs fails the test. A diff built another way (a key held in a variable) is not seen, so a module that gains
  one that way must say so in its attributes and will fail here until the scan reads it.
- platform: a module whose work is all on the controller (no AnsibleModule) declares `platforms: all`; every
  other module names the platforms of the hosts it runs on.

The documentation checked is the one ansible-doc shows: the module's DOCUMENTATION with its
extends_documentation_fragment merged by Ansible's own add_fragments, from the collection's fragment files."""

from __future__ import annotations

import ast
import copy
import functools
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml
from ansible.utils.plugin_docs import add_fragments

ROOT = Path(__file__).resolve().parents[2]
MODULES = sorted((ROOT / "plugins" / "modules").glob("*.py"))
ACTIONS = ROOT / "plugins" / "action"
FRAGMENTS = ROOT / "plugins" / "doc_fragments"
PLUGINS = ROOT / "plugins"
PREFIX = "isaacsim.fleet."
PACKAGE = "ansible_collections.isaacsim.fleet.plugins."
SUPPORT = {"full", "partial", "none", "N/A"}
PLATFORMS = {"posix", "debian", "all"}

# module -> why the diff scan finds a diff its code never returns
DIFF_SCAN_MISREADS = {
    "isaac_sim_plan": "its host facts import module_utils/host/host_service.py for seen() (whether a host service is "
    "as the deploy wants it); Service.apply, the one function there that returns a diff, is "
    "isaac_sim_host_service's",
}

# option -> (the modules that document it themselves, why their texts differ). Every option that more than one
# module takes is either from one doc fragment in all of them, or here with exactly the modules that write it.
OWN_TEXTS = {
    "action": (
        {"isaac_sim_audit", "isaac_sim_lifecycle"},
        "what the call does: each module its own choices",
    ),
    "allowed_docker_args": (
        {"isaac_sim_plan"},
        "the plan's allows arguments of the instances' and companions' docker_args, matched on what Docker makes "
        "of them; the run modules' (isaacsim.fleet.runs) allow a compose service's confinement keys",
    ),
    "gpus": (
        {"isaac_sim_warm_cache"},
        "the host's GPUs as the plan's probe found them (dicts: index, name), for the cache key; the run modules' "
        "(isaacsim.fleet.runs) are GPU ids to give services",
    ),
    "image_id": (
        {"isaac_sim_lifecycle", "isaac_sim_warm_cache"},
        "the same id, but required by isaac_sim_warm_cache and defaulting to unknown in isaac_sim_lifecycle, and "
        "each says what that value does there",
    ),
    "instances": (
        {"isaac_sim_info", "isaac_sim_test_suite"},
        "the instances to report, against the instances runs may borrow",
    ),
    "key": (
        {"isaac_sim_audit", "isaac_sim_warm_cache"},
        "the registry key looked for on the host, against the id of a cache key",
    ),
    "mirror": (
        {"isaac_sim_image_pin", "isaac_sim_mirror_seed"},
        "the same HOST:PORT, optional for the pin (empty: no mirror) and required by the seed, which runs on it",
    ),
    "name": (
        {"isaac_sim_door_token", "isaac_sim_experience", "isaac_sim_host_service"},
        "an experience's name, against a systemd unit's and an API token's",
    ),
    "path": (
        {"docker_daemon_config", "isaac_sim_results_lock"},
        "Docker's daemon.json, against a results directory on the controller",
    ),
    "plan": (
        {"isaac_sim_lifecycle", "isaac_sim_warm_cache"},
        "the same plan, but required by isaac_sim_warm_cache and only by action=apply in isaac_sim_lifecycle",
    ),
    "public_address": (
        {"isaac_sim_info", "isaac_sim_plan"},
        "the plan's is the address the instances are deployed with; the status's overrides it in the URLs it "
        "reports, by default the deployed one",
    ),
    "ready_timeout": (
        {"isaac_sim_mirror_seed", "isaac_sim_plan"},
        "the loopback registry's first answer, against an instance's ready line",
    ),
    "release": (
        {"isaac_sim_plan", "nvidia_driver_check"},
        "the plan requires it and refuses an unknown one with its own message; the driver check has the release "
        "table's choices and a default",
    ),
    "state": (
        {
            "isaac_sim_door_token",
            "isaac_sim_host_service",
            "isaac_sim_lock",
            "isaac_sim_results_lock",
            "isaac_sim_train_job",
            "isaac_sim_warm_cache",
        },
        "what the call does: each module its own states",
    ),
    "timeout": (
        {"isaac_sim_audit", "isaac_sim_experience"},
        "a port's answer, against a whole run",
    ),
}


@functools.cache
def _source(path: Path) -> ast.Module:
    return ast.parse(path.read_text(), str(path))


def _constant(tree: ast.Module, name: str):
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == name for t in node.targets):
            return node.value.value
    return None


def _fragment_class(path: Path) -> dict:
    """The string attributes of a fragment file's ModuleDocFragment (DOCUMENTATION, PLATFORM, ...)."""
    for node in _source(path).body:
        if isinstance(node, ast.ClassDef) and node.name == "ModuleDocFragment":
            return {
                t.id: item.value.value
                for item in node.body
                if isinstance(item, ast.Assign) and isinstance(item.value, ast.Constant)
                for t in item.targets
                if isinstance(t, ast.Name)
            }
    raise AssertionError(f"{path.relative_to(ROOT)}: no class ModuleDocFragment")


class _FragmentLoader:
    """Ansible's fragment_loader for this collection's fragments: add_fragments asks it for
    isaacsim.fleet.NAME (and, failing that, splits NAME.VAR off itself)."""

    def get(self, name: str):
        if not name.startswith(PREFIX) or not (FRAGMENTS / f"{name[len(PREFIX) :]}.py").is_file():
            return None
        return SimpleNamespace(ansible_name=name, **_fragment_class(FRAGMENTS / f"{name[len(PREFIX) :]}.py"))


def raw_doc(path: Path) -> dict:
    return yaml.safe_load(_constant(_source(path), "DOCUMENTATION"))


def resolved_doc(path: Path) -> dict:
    """The documentation as ansible-doc shows it: the fragments merged in by Ansible's own code."""
    doc = copy.deepcopy(raw_doc(path))
    add_fragments(doc, str(path), _FragmentLoader(), is_module=True)
    return doc


def fragment_options(slug: str) -> dict:
    """The options of one fragment, as extends_documentation_fragment names it."""
    doc: dict = {"extends_documentation_fragment": [slug], "options": {}}
    add_fragments(doc, str(FRAGMENTS), _FragmentLoader(), is_module=True)
    return doc["options"]


def check_mode_in_code(name: str) -> bool | None:
    """Whether Ansible runs the module's task in check mode (None: the source does not say)."""
    for node in ast.walk(_source(ROOT / "plugins" / "modules" / f"{name}.py")):
        if isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", "")) == "AnsibleModule":
            flag = next((k.value for k in node.keywords if k.arg == "supports_check_mode"), None)
            module = isinstance(flag, ast.Constant) and flag.value is True
            break
    else:
        module = None  # no module code: the action plugin does the work
    action = ACTIONS / f"{name}.py"
    plugin = True  # ActionBase's own default
    if action.is_file():
        for node in ast.walk(_source(action)):
            if isinstance(node, ast.Assign) and any(
                getattr(t, "id", "") == "_supports_check_mode" for t in node.targets
            ):
                plugin = node.value.value is True
    elif module is None:
        return None
    return plugin and module is not False


def _imports(path: Path) -> set:
    """The collection's files that one file imports."""
    found = set()
    for node in ast.walk(_source(path)):
        names = []
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith(PACKAGE):
            base = node.module[len(PACKAGE) :].replace(".", "/")
            names = [f"{base}/{alias.name}" for alias in node.names] + [base]
        elif isinstance(node, ast.Import):
            names = [a.name[len(PACKAGE) :].replace(".", "/") for a in node.names if a.name.startswith(PACKAGE)]
        found.update(PLUGINS / f"{name}.py" for name in names if (PLUGINS / f"{name}.py").is_file())
    return found


def code_of(name: str) -> set:
    """The module, its action plugin and every file of the collection they import, however indirectly."""
    todo = [p for p in (PLUGINS / "modules" / f"{name}.py", ACTIONS / f"{name}.py") if p.is_file()]
    seen = set()
    while todo:
        path = todo.pop()
        if path not in seen:
            seen.add(path)
            todo += _imports(path)
    return seen


def diff_keys(path: Path) -> list:
    """Lines of one file that put a "diff" key into a result."""

    def puts_diff(node) -> bool:
        if isinstance(node, ast.Dict):  # {"diff": ...}
            return any(isinstance(k, ast.Constant) and k.value == "diff" for k in node.keys)
        if isinstance(node, ast.Subscript):  # result["diff"] = ...
            return (
                isinstance(node.ctx, ast.Store) and isinstance(node.slice, ast.Constant) and node.slice.value == "diff"
            )
        if isinstance(node, ast.Call):  # dict(diff=...), result.update(diff=...), module.exit_json(diff=...)
            func = getattr(node.func, "attr", getattr(node.func, "id", ""))
            return func in ("dict", "update", "exit_json", "fail_json") and any(k.arg == "diff" for k in node.keywords)
        return False

    return [node.lineno for node in ast.walk(_source(path)) if puts_diff(node)]


def diff_in_code(name: str) -> list:
    """Where the code of a module can return a diff: 'file:line' each."""
    return sorted(f"{path.relative_to(ROOT)}:{line}" for path in code_of(name) for line in diff_keys(path))


def _names(paths):
    return [p.stem for p in paths]


@pytest.mark.parametrize("path", MODULES, ids=_names(MODULES))
def test_declares_check_diff_and_platform_with_the_shared_descriptions(path):
    raw, doc = raw_doc(path), resolved_doc(path)
    fragments = raw.get("extends_documentation_fragment") or []
    assert {"isaacsim.fleet.attributes", "isaacsim.fleet.attributes.platform"} <= set(fragments), (
        f"{path.name}: extends_documentation_fragment lacks isaacsim.fleet.attributes or .platform"
    )
    for name in ("check_mode", "diff_mode", "platform"):
        attribute = doc.get("attributes", {}).get(name)
        assert attribute, f"{path.name}: no attributes.{name}"
        assert attribute.get("description"), f"{path.name}: attributes.{name} has no description"
        assert "description" not in raw["attributes"][name], (
            f"{path.name}: attributes.{name} writes its own description; the fragment's is shared, say the rest in "
            "details"
        )
    for name in ("check_mode", "diff_mode"):
        attribute = doc["attributes"][name]
        assert attribute.get("support") in SUPPORT, f"{path.name}: attributes.{name}.support {attribute.get('support')}"
        if attribute["support"] == "partial":
            assert attribute.get("details"), f"{path.name}: partial {name} without details of what is left out"
    assert doc["attributes"]["platform"].get("platforms") in PLATFORMS, f"{path.name}: attributes.platform.platforms"


@pytest.mark.parametrize("path", MODULES, ids=_names(MODULES))
def test_check_mode_support_is_none_exactly_when_ansible_skips_the_task(path):
    runs = check_mode_in_code(path.stem)
    assert runs is not None, f"{path.name}: neither an AnsibleModule nor an action plugin says how check mode goes"
    support = resolved_doc(path)["attributes"]["check_mode"]["support"]
    if runs:
        assert support != "none", f"{path.name}: the code runs in check mode, the documentation says it does not"
    else:
        assert support == "none", f"{path.name}: Ansible skips it in check mode, the documentation says {support}"


@pytest.mark.parametrize("path", MODULES, ids=_names(MODULES))
def test_diff_mode_support_is_given_exactly_when_the_code_returns_a_diff(path):
    found = diff_in_code(path.stem)
    returns = bool(found) and path.stem not in DIFF_SCAN_MISREADS
    support = resolved_doc(path)["attributes"]["diff_mode"]["support"]
    if returns:
        assert support in ("full", "partial"), f"{path.name}: returns a diff ({', '.join(found)}), documents {support}"
    else:
        assert support in ("none", "N/A"), f"{path.name}: documents diff_mode {support}; no code of it returns a diff"


@pytest.mark.parametrize("name", sorted(DIFF_SCAN_MISREADS))
def test_every_diff_scan_misread_is_still_one(name):
    assert diff_in_code(name), f"DIFF_SCAN_MISREADS[{name!r}]: the scan finds no diff any more; drop the entry"


@pytest.mark.parametrize("path", MODULES, ids=_names(MODULES))
def test_action_attribute_exactly_where_there_is_an_action_plugin(path):
    raw, doc = raw_doc(path), resolved_doc(path)
    attribute = doc["attributes"].get("action")
    if (ACTIONS / path.name).is_file():
        assert "isaacsim.fleet.attributes.action" in raw["extends_documentation_fragment"], path.name
        assert attribute and attribute.get("support") == "full" and attribute.get("description"), path.name
        assert "description" not in raw["attributes"]["action"], f"{path.name}: action writes its own description"
    else:
        assert attribute is None, f"{path.name}: declares the action attribute without plugins/action/{path.name}"


@pytest.mark.parametrize("path", MODULES, ids=_names(MODULES))
def test_platform_all_exactly_for_the_controller_only_modules(path):
    controller_only = "AnsibleModule(" not in path.read_text()
    platforms = resolved_doc(path)["attributes"]["platform"]["platforms"]
    where = "runs on the controller only" if controller_only else "runs on a host"
    assert (platforms == "all") == controller_only, f"{path.name}: platforms {platforms}, but it {where}"


def test_an_option_of_several_modules_has_one_text():
    """Each option name of more than one module comes from one fragment everywhere, but in the modules OWN_TEXTS
    lists for it; a module never writes its own text for an option one of its fragments gives (its text would
    replace the fragment's there alone)."""
    own, shared = {}, {}
    for path in MODULES:
        raw = raw_doc(path)
        for option in raw.get("options") or {}:
            own.setdefault(option, set()).add(path.stem)
        for slug in raw.get("extends_documentation_fragment") or []:
            for option in fragment_options(slug):
                assert option not in (raw.get("options") or {}), (
                    f"{path.name}: documents {option} itself and has it from {slug}; drop its own text"
                )
                shared.setdefault(option, {}).setdefault(slug, set()).add(path.stem)
    problems = []
    for option in sorted(set(own) | set(shared)):
        writers, slugs = own.get(option, set()), shared.get(option, {})
        if len(slugs) > 1:
            problems.append(f"{option}: from more than one fragment ({', '.join(sorted(slugs))})")
        if len(writers) + sum(len(m) for m in slugs.values()) < 2:
            assert option not in OWN_TEXTS, f"OWN_TEXTS[{option!r}]: only one module takes it now; drop the entry"
            continue
        allowed = OWN_TEXTS.get(option, (set(), ""))[0]
        if writers != allowed:
            problems.append(
                f"{option}: written by {', '.join(sorted(writers)) or 'no module'} itself, OWN_TEXTS allows "
                f"{', '.join(sorted(allowed)) or 'none'}. Fix: move the text to a fragment in plugins/doc_fragments "
                "(one text for every module), or list the module in OWN_TEXTS with why its option differs"
            )
    assert not problems, "\n".join(problems)


def test_every_fragment_is_used_and_an_option_fragment_by_two_modules():
    users: dict = {}
    for path in MODULES:
        for slug in raw_doc(path).get("extends_documentation_fragment") or []:
            users.setdefault(slug, set()).add(path.stem)
    for path in sorted(FRAGMENTS.glob("*.py")):
        for var, text in _fragment_class(path).items():
            content = yaml.safe_load(text) or {}
            if not content.get("options") and not content.get("attributes"):
                continue  # a file's empty DOCUMENTATION, where its modules take its parts by name
            slug = PREFIX + path.stem + ("" if var == "DOCUMENTATION" else f".{var.lower()}")
            who = users.get(slug, set())
            assert who, f"{slug}: no module extends it"
            if content.get("options"):
                assert len(who) > 1, f"{slug}: only {', '.join(who)} takes it; its options belong in that module"
