"""tools/changelog-check: version_added against the releases in changelogs/changelog.yaml and galaxy.yml, a change
without a changelog fragment in a real git history (each rule shown to fail), and antsibull-changelog's lint where
it is installed.

The tool is a script without a .py name, loaded here from its file; the tests work on collections and git
repositories of their own in tmp_path (plain pytest and ansible-test units alike: the latter's copy of the tree has
tools/ but no .git)."""

from __future__ import annotations

import importlib.machinery
import importlib.util
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[3]
TOOL = ROOT / "tools" / "changelog-check"


def load_tool():
    loader = importlib.machinery.SourceFileLoader("changelog_check", str(TOOL))
    spec = importlib.util.spec_from_loader("changelog_check", loader)
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    return module


check = load_tool()

GALAXY = {"namespace": "demo", "name": "fleet", "version": "0.2.0", "dependencies": {"community.docker": ">=4.0.0"}}


def module_source(name: str, version_added: str, option_version: str | None = None) -> str:
    option = f"\n    version_added: {option_version!r}" if option_version else ""
    return (
        'DOCUMENTATION = r"""\n'
        f"module: {name}\n"
        "short_description: A module\n"
        f'version_added: "{version_added}"\n'
        "options:\n"
        "  size:\n"
        "    description: A size.\n"
        f"    type: int{option}\n"
        '"""\n'
    )


def filter_source(name: str, version_added: str) -> str:
    """A filter's documentation; version_added as written in YAML."""
    return f'DOCUMENTATION = """\nname: {name}\nshort_description: A filter\nversion_added: {version_added}\n"""\n'


def write(root: Path, path: str, text: str) -> None:
    target = root / path
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(text)


def collection(root: Path, galaxy_version: str = "0.2.0", releases: dict | None = None) -> Path:
    """A collection whose changelog has release 0.1.0 listing module a, filter f and role r."""
    if releases is None:
        releases = {
            "0.1.0": {
                "release_date": "2026-11-22",
                "modules": [{"name": "a", "description": "A module.", "namespace": ""}],
                "plugins": {"filter": [{"name": "f", "description": "A filter.", "namespace": None}]},
                "objects": {"role": [{"name": "r", "description": "A role.", "namespace": None}]},
            }
        }
    write(root, "galaxy.yml", yaml.safe_dump(dict(GALAXY, version=galaxy_version)))
    write(root, "changelogs/changelog.yaml", yaml.safe_dump({"ancestor": None, "releases": releases}))
    write(root, "plugins/modules/a.py", module_source("a", "0.1.0"))
    write(root, "plugins/filter/f.py", filter_source("f", '"0.1.0"'))
    write(
        root,
        "roles/r/meta/argument_specs.yml",
        "---\nargument_specs:\n  main:\n    short_description: R\n    version_added: '0.1.0'\n    options: {}\n",
    )
    return root


# ------------------------------------------------------------------ version_added


def test_version_added_of_a_release_or_of_the_release_in_progress_passes(tmp_path):
    root = collection(tmp_path)
    write(root, "plugins/modules/b.py", module_source("b", "0.2.0", option_version="0.2.0"))
    assert check.version_added_errors(root) == []


def test_version_added_of_no_release_fails_naming_the_file_and_the_fix(tmp_path):
    root = collection(tmp_path)
    write(root, "plugins/modules/b.py", module_source("b", "0.4.0"))
    errors = check.version_added_errors(root)
    assert len(errors) == 1
    assert errors[0].startswith("plugins/modules/b.py: version_added '0.4.0'")
    assert "neither a release in changelogs/changelog.yaml (0.1.0) nor galaxy.yml's version 0.2.0" in errors[0]
    assert 'Fix: version_added: "0.2.0"' in errors[0]


def test_an_option_s_version_added_is_checked_too(tmp_path):
    root = collection(tmp_path)
    write(root, "plugins/modules/a.py", module_source("a", "0.1.0", option_version="0.3.0"))
    (error,) = check.version_added_errors(root)
    assert "plugins/modules/a.py: version_added '0.3.0' (at options.size)" in error


def test_a_role_entry_point_s_version_added_is_checked(tmp_path):
    root = collection(tmp_path)
    spec = root / "roles/r/meta/argument_specs.yml"
    spec.write_text(spec.read_text().replace("'0.1.0'", "'1.0.0'"))
    (error,) = check.version_added_errors(root)
    assert error.startswith("roles/r/meta/argument_specs.yml: version_added '1.0.0' (at main)")


def test_a_version_added_that_is_not_a_string_is_refused(tmp_path):
    root = collection(tmp_path)
    write(root, "plugins/filter/f.py", filter_source("f", "0.1"))
    (error,) = check.version_added_errors(root)
    assert "version_added 0.1 is not a string" in error


def test_a_documentation_that_does_not_parse_is_named(tmp_path):
    root = collection(tmp_path)
    write(root, "plugins/filter/broken.py", 'DOCUMENTATION = """\nname: [broken\n"""\n')
    (error,) = check.version_added_errors(root)
    assert error.startswith("plugins/filter/broken.py: its DOCUMENTATION does not parse")


def test_a_release_that_does_not_list_the_plugin_means_it_came_after_that_release(tmp_path):
    """A module added after 0.1.0 that copied version_added 0.1.0: the release's entry does not list it."""
    root = collection(tmp_path)
    write(root, "plugins/modules/late.py", module_source("late", "0.1.0"))
    write(root, "plugins/filter/g.py", filter_source("g", '"0.1.0"'))
    errors = check.version_added_errors(root)
    assert len(errors) == 2
    assert any(e.startswith("plugins/modules/late.py:") and "does not list modules late" in e for e in errors)
    assert any(e.startswith("plugins/filter/g.py:") and "does not list filter g" in e for e in errors)
    assert all('Fix: version_added: "0.2.0"' in e for e in errors)


def test_a_plugin_added_after_a_release_while_galaxy_still_names_that_release(tmp_path):
    root = collection(tmp_path, galaxy_version="0.1.0")
    write(root, "plugins/modules/late.py", module_source("late", "0.1.0"))
    (error,) = check.version_added_errors(root)
    assert "set galaxy.yml's version to the next release" in error


def test_galaxy_version_below_the_latest_release_fails(tmp_path):
    root = collection(tmp_path, galaxy_version="0.0.9")
    errors = check.version_added_errors(root)
    assert errors[0] == (
        "galaxy.yml: version 0.0.9 is below the latest release in changelogs/changelog.yaml, 0.1.0. "
        "Fix: set it to the next release"
    )


def test_this_collection_s_version_added_name_its_releases():
    assert check.version_added_errors(ROOT) == []


# ------------------------------------------------------------------ a change without a fragment


@pytest.fixture
def repo(tmp_path, monkeypatch):
    """A git repository whose first commit is a release (it adds changelogs/changelog.yaml)."""
    for key, value in {
        "GIT_CONFIG_GLOBAL": "/dev/null",
        "GIT_CONFIG_NOSYSTEM": "1",
        "GIT_AUTHOR_NAME": "t",
        "GIT_AUTHOR_EMAIL": "t@example.com",
        "GIT_COMMITTER_NAME": "t",
        "GIT_COMMITTER_EMAIL": "t@example.com",
    }.items():
        monkeypatch.setenv(key, value)
    root = collection(tmp_path / "repo")
    write(root, "changelogs/fragments/.keep", "")
    write(root, "README.md", "readme\n")
    git(root, "init", "-q", "-b", "main")
    commit(root, "Release 0.1.0")
    return root


def git(root: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, check=True).stdout


def commit(root: Path, message: str) -> str:
    git(root, "add", "-A")
    git(root, "commit", "-q", "-m", message)
    return git(root, "rev-parse", "HEAD").strip()


def fragment(root: Path, name: str = "change.yml") -> None:
    write(root, f"changelogs/fragments/{name}", "---\nbugfixes:\n  - A fix.\n")


def test_the_release_commit_alone_passes(repo):
    assert check.fragment_errors(repo) == []


def test_a_commit_that_changes_a_plugin_without_a_fragment_fails(repo):
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    sha = commit(repo, "Change a")
    (error,) = check.fragment_errors(repo)
    assert error.startswith(f'commit {sha[:12]} ("Change a") changes plugins/modules/a.py without a changelog fragment')
    assert "Fix: add a fragment, changelogs/fragments/<topic>.yml" in error
    assert f"Changelog-For: {sha[:12]}" in error


@pytest.mark.parametrize("path", ["roles/r/tasks/main.yml", "playbooks/deploy.yml", "meta/runtime.yml"])
def test_roles_playbooks_and_meta_are_watched_too(repo, path):
    write(repo, path, "---\n")
    commit(repo, f"Add {path}")
    (error,) = check.fragment_errors(repo)
    assert f"changes {path} without" in error


def test_a_commit_with_its_fragment_passes(repo):
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    fragment(repo)
    commit(repo, "Change a")
    assert check.fragment_errors(repo) == []


def test_a_commit_that_only_removes_a_fragment_has_no_entry(repo):
    fragment(repo)
    commit(repo, "A fragment")
    (repo / "changelogs/fragments/change.yml").unlink()
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    commit(repo, "Change a, drop the fragment")
    (error,) = check.fragment_errors(repo)
    assert "Change a, drop the fragment" in error


def test_the_no_changelog_marker_lets_a_commit_through(repo):
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# comment\n")
    commit(repo, "Comment in a\n\nNothing users see. [No changelog]")
    assert check.fragment_errors(repo) == []


def test_a_later_commit_with_a_fragment_covers_a_commit_it_names(repo):
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    sha = commit(repo, "Change a")
    write(repo, "README.md", "readme, again\n")
    commit(repo, f"Docs\n\nChangelog-For: {sha[:10]}")  # no fragment: it covers nothing
    assert len(check.fragment_errors(repo)) == 1
    fragment(repo)
    commit(repo, f"The fragment of a's change\n\nChangelog-For: {sha[:10]}")
    assert check.fragment_errors(repo) == []


def test_a_commit_outside_the_watched_paths_needs_no_fragment(repo):
    write(repo, "README.md", "more\n")
    write(repo, "tests/unit/test_x.py", "\n")
    commit(repo, "Docs and tests")
    assert check.fragment_errors(repo) == []


def test_galaxy_s_version_bump_needs_no_fragment_but_its_dependencies_do(repo):
    write(repo, "galaxy.yml", yaml.safe_dump(dict(GALAXY, version="0.3.0")))
    commit(repo, "Next version 0.3.0")
    assert check.fragment_errors(repo) == []
    write(repo, "galaxy.yml", yaml.safe_dump(dict(GALAXY, version="0.3.0", dependencies={"ansible.posix": "*"})))
    commit(repo, "Depend on ansible.posix")
    (error,) = check.fragment_errors(repo)
    assert "changes galaxy.yml without" in error


def test_only_commits_since_the_release_commit_are_read(repo):
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    commit(repo, "Change a")
    assert len(check.fragment_errors(repo)) == 1
    changes = repo / "changelogs/changelog.yaml"
    changes.write_text(changes.read_text() + "# the next release\n")
    commit(repo, "Release 0.2.0")
    assert check.fragment_errors(repo) == []


def test_a_history_without_a_changelog_yaml_has_no_commit_checked(tmp_path, repo):
    git(repo, "rm", "-q", "-r", "changelogs")
    git(repo, "commit", "-q", "--amend", "-m", "Before the changelog")
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    commit(repo, "Change a")
    assert check.fragment_errors(repo, worktree=False) == []


def test_the_working_tree_is_held_to_the_same_rule(repo):
    write(repo, "roles/r/tasks/main.yml", "---\n")  # untracked
    (error,) = check.fragment_errors(repo)
    assert error.startswith("the working tree changes roles/r/tasks/main.yml without a changelog fragment")
    assert check.fragment_errors(repo, worktree=False) == []
    fragment(repo)  # untracked too
    assert check.fragment_errors(repo) == []


def test_an_uncommitted_change_to_a_tracked_plugin_is_seen(repo):
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    (error,) = check.fragment_errors(repo)
    assert "the working tree changes plugins/modules/a.py" in error


def test_a_shallow_clone_reads_the_commits_it_holds(repo, tmp_path, capsys):
    """CI may clone with --depth: the oldest commit held seems to add every file, changelog.yaml too, so the
    commits after it are read (none at depth 1), never an error for the history it lacks."""
    write(repo, "README.md", "one\n")
    commit(repo, "One")
    write(repo, "plugins/modules/late.py", module_source("late", "0.2.0"))
    commit(repo, "A module without a fragment")
    write(repo, "README.md", "two\n")
    commit(repo, "Two")
    one, two = tmp_path / "one", tmp_path / "two"
    git(tmp_path, "clone", "-q", "--depth", "1", f"file://{repo}", str(one))
    assert check.fragment_errors(one) == []
    assert "a shallow clone" in capsys.readouterr().out
    # deep enough to hold the commit without a fragment after its boundary commit (One, not the release): found
    git(tmp_path, "clone", "-q", "--depth", "3", f"file://{repo}", str(two))
    assert git(two, "rev-parse", "--is-shallow-repository").strip() == "true"
    (error,) = check.fragment_errors(two)
    assert "plugins/modules/late.py" in error


def test_main_exits_1_and_names_each_error(repo, capsys, monkeypatch):
    monkeypatch.setattr(check, "lint_errors", lambda root: [])
    assert check.main(["--root", str(repo)]) == 0
    write(repo, "plugins/modules/b.py", module_source("b", "9.0.0"))
    assert check.main(["--root", str(repo)]) == 1
    err = capsys.readouterr().err
    assert "changelog-check: plugins/modules/b.py: version_added '9.0.0'" in err
    assert "changelog-check: the working tree changes plugins/modules/b.py" in err


# ------------------------------------------------------------------ antsibull-changelog lint

needs_antsibull = pytest.mark.skipif(
    check.antsibull_changelog() is None, reason="antsibull-changelog is not installed (requirements.txt)"
)


@pytest.fixture
def linted(tmp_path):
    """This collection's changelog configuration, history and CHANGELOG.md in a directory of their own."""
    root = tmp_path / "collection"
    shutil.copytree(ROOT / "changelogs", root / "changelogs", ignore=shutil.ignore_patterns(".plugin-cache.yaml"))
    for name in ("galaxy.yml", "CHANGELOG.md"):
        shutil.copy(ROOT / name, root / name)
    return root


@needs_antsibull
def test_this_collection_s_changelog_lints_and_is_generated(linted):
    assert check.lint_errors(linted) == []


@needs_antsibull
def test_a_broken_fragment_fails_the_lint_naming_it(linted):
    write(linted, "changelogs/fragments/broken.yml", "---\nnew_things:\n  - Something.\n")
    (error,) = check.lint_errors(linted)
    assert "changelogs/fragments/broken.yml" in error
    assert "invalid section: new_things" in error


@needs_antsibull
def test_a_hand_edited_changelog_md_fails(linted):
    (linted / "CHANGELOG.md").write_text((linted / "CHANGELOG.md").read_text() + "\n* a line by hand\n")
    (error,) = check.lint_errors(linted)
    assert error.startswith("CHANGELOG.md is not what antsibull-changelog generates")
