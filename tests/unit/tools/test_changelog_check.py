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


CHANGES_010 = """
release_date: "2026-11-22"
modules: [{name: a, description: A module., namespace: ""}]
plugins: {filter: [{name: f, description: A filter., namespace: null}]}
objects: {role: [{name: r, description: A role., namespace: null}]}
"""


def collection(root: Path, galaxy_version: str = "0.2.0", releases: dict | None = None) -> Path:
    """A collection whose changelog has release 0.1.0 listing module a, filter f and role r."""
    if releases is None:
        releases = {"0.1.0": yaml.safe_load(CHANGES_010)}
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


def test_a_plugin_in_a_subdirectory_is_checked(tmp_path):
    """H10: plugins/modules/sub/x.py is read too."""
    root = collection(tmp_path)
    write(root, "plugins/modules/sub/__init__.py", "")
    write(root, "plugins/modules/sub/x.py", module_source("x", "7.0.0"))
    (error,) = check.version_added_errors(root)
    assert error.startswith("plugins/modules/sub/x.py: version_added '7.0.0'")


@pytest.mark.parametrize("spec_file", ["meta/argument_specs.yaml", "meta/main.yml"])
def test_a_role_s_argument_specs_are_read_from_each_place_ansible_reads(tmp_path, spec_file):
    root = collection(tmp_path)
    write(
        root,
        f"roles/s/{spec_file}",
        "---\nargument_specs:\n  main:\n    short_description: S\n    version_added: '5.0.0'\n",
    )
    (error,) = check.version_added_errors(root)
    assert error.startswith(f"roles/s/{spec_file}: version_added '5.0.0' (at main)")


def role_with_entry_point(root: Path, entry_version: str) -> None:
    write(
        root,
        "roles/r/meta/argument_specs.yml",
        "---\nargument_specs:\n  main:\n    short_description: R\n    version_added: '0.1.0'\n"
        f"  check:\n    short_description: C\n    version_added: '{entry_version}'\n",
    )


def test_an_entry_point_cannot_predate_its_role(tmp_path):
    root = collection(tmp_path, releases={"0.0.1": {}, "0.1.0": yaml.safe_load(CHANGES_010)})
    role_with_entry_point(root, "0.0.1")
    (error,) = check.version_added_errors(root)
    assert "version_added '0.0.1' (at check) is before the role's own version_added '0.1.0'" in error


def test_an_entry_point_missing_at_its_release_s_tag_came_after_it(repo):
    git(repo, "tag", "0.1.0")
    role_with_entry_point(repo, "0.1.0")  # copied from main, added after 0.1.0
    (error,) = check.version_added_errors(repo)
    assert "role r had no entry point check at that release's tag" in error
    role_with_entry_point(repo, "0.2.0")
    assert check.version_added_errors(repo) == []


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
    commit(repo, "Comment in a [no changelog]\n\nNothing users see.")
    assert check.fragment_errors(repo) == []


@pytest.mark.parametrize(
    "message",
    [
        "Comment in a\n\nNothing users see. [no changelog]",  # not on the subject line
        "Comment in a [No changelog]",  # not in lower case
        "Comment in a [NO CHANGELOG]",
        "Comment in a, not[no changelog]",  # not a word of its own
    ],
)
def test_the_no_changelog_marker_counts_only_on_the_subject_line_as_written(repo, message):
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# comment\n")
    commit(repo, message)
    (error,) = check.fragment_errors(repo)
    assert "changes plugins/modules/a.py without a changelog fragment" in error


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


def release(root: Path, version: str) -> None:
    """What antsibull-changelog release does: a release in changelog.yaml, its fragments consumed."""
    changes = root / "changelogs/changelog.yaml"
    data = yaml.safe_load(changes.read_text())
    data["releases"][version] = {"release_date": "2026-12-01"}
    changes.write_text(yaml.safe_dump(data))
    for path in (root / "changelogs/fragments").glob("*.y*ml"):
        path.unlink()


def test_only_commits_since_the_release_commit_are_read(repo):
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    commit(repo, "Change a")
    assert len(check.fragment_errors(repo)) == 1
    release(repo, "0.2.0")
    commit(repo, "Release 0.2.0")
    assert check.fragment_errors(repo) == []


def test_a_commit_that_touches_changelog_yaml_without_a_release_excuses_nothing(repo):
    """H2: a comment in changelog.yaml neither makes that commit the release commit nor gives it an entry."""
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    commit(repo, "Change a")
    changes = repo / "changelogs/changelog.yaml"
    changes.write_text(changes.read_text() + "# a comment\n")
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed again\n")
    commit(repo, "A comment in the changelog, and a again")
    errors = check.fragment_errors(repo)
    assert len(errors) == 2
    assert all("since release 0.1.0's commit" in e for e in errors)


def test_the_latest_release_s_tag_is_the_base(repo):
    write(repo, "README.md", "later\n")
    commit(repo, "Docs")
    git(repo, "tag", "0.1.0")  # the release, tagged on a later commit: what comes after the tag is read
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    sha = commit(repo, "Change a")
    (error,) = check.fragment_errors(repo)
    assert error.startswith(f"commit {sha[:12]}")
    assert f"since release 0.1.0's commit {git(repo, 'rev-parse', 'HEAD~1').strip()[:12]}" in error


def test_a_blank_line_added_to_an_old_fragment_covers_nothing(repo):
    """H3: a fragment covers the commit that adds it or gives it a new entry, not one that only touches it."""
    fragment(repo)
    write(repo, "README.md", "docs\n")
    commit(repo, "A fragment")
    path = repo / "changelogs/fragments/change.yml"
    path.write_text(path.read_text() + "\n")
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    commit(repo, "Change a, a blank line in the fragment")
    (error,) = check.fragment_errors(repo)
    assert "Change a, a blank line" in error
    path.write_text(path.read_text() + "  - Another fix.\n")
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed again\n")
    commit(repo, "Change a again, a new entry")
    assert len(check.fragment_errors(repo)) == 1  # the new entry covers its own commit


def test_a_renamed_fragment_covers_nothing(repo):
    fragment(repo)
    commit(repo, "A fragment")
    (repo / "changelogs/fragments/change.yml").rename(repo / "changelogs/fragments/renamed.yml")
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    commit(repo, "Change a, rename the fragment")
    (error,) = check.fragment_errors(repo)
    assert "Change a, rename" in error


def test_the_working_tree_needs_a_new_fragment_or_entry_too(repo):
    fragment(repo)
    commit(repo, "A fragment")
    path = repo / "changelogs/fragments/change.yml"
    path.write_text(path.read_text() + "\n")
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    (error,) = check.fragment_errors(repo)
    assert error.startswith("the working tree changes plugins/modules/a.py")
    path.write_text(path.read_text() + "  - Another fix.\n")
    assert check.fragment_errors(repo) == []


def test_a_fragment_removed_later_no_longer_covers_its_commit(repo):
    """H4: the covering fragment must still be there at HEAD, unless a release consumed it."""
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    fragment(repo)
    sha = commit(repo, "Change a")
    git(repo, "rm", "-q", "changelogs/fragments/change.yml")
    git(repo, "commit", "-q", "-m", "Drop the fragment")
    (error,) = check.fragment_errors(repo)
    assert error.startswith(f"commit {sha[:12]}")
    assert "its fragment changelogs/fragments/change.yml was removed since" in error
    git(repo, "reset", "-q", "--hard", sha)
    release(repo, "0.2.0")  # the release consumes it
    commit(repo, "Release 0.2.0")
    assert check.fragment_errors(repo) == []


def test_a_fragment_removed_in_the_working_tree_no_longer_covers(repo):
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    fragment(repo)
    commit(repo, "Change a")
    (repo / "changelogs/fragments/change.yml").unlink()
    (error,) = check.fragment_errors(repo)
    assert '("Change a")' in error
    assert check.fragment_errors(repo, worktree=False) == []


def test_a_hidden_fragment_covers_nothing_and_is_named(repo):
    """H5: antsibull-changelog never reads .name.yml."""
    fragment(repo, ".change.yml")
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    commit(repo, "Change a, a hidden fragment")
    (error,) = check.fragment_errors(repo)
    assert "Change a, a hidden fragment" in error
    (error,) = check.fragment_file_errors(repo)
    assert error.startswith("changelogs/fragments/.change.yml: antsibull-changelog ignores a fragment")


@pytest.mark.parametrize(
    "text", ["---\nminor_changes: []\n", '---\nminor_changes: [""]\n', "---\nbugfixes:\n  - A fix.\n  - ' '\n"]
)
def test_a_fragment_without_a_non_empty_entry_fails(tmp_path, text):
    """H6: antsibull-changelog lint lets an empty section through."""
    write(tmp_path, "changelogs/fragments/empty.yml", text)
    write(tmp_path, "changelogs/fragments/good.yml", "---\nbugfixes:\n  - A fix.\nrelease_summary: Summary.\n")
    (error,) = check.fragment_file_errors(tmp_path)
    assert error.startswith("changelogs/fragments/empty.yml: ")
    assert "has no entry or an empty one" in error


def test_an_empty_fragment_covers_nothing(repo):
    write(repo, "changelogs/fragments/empty.yml", '---\nminor_changes: [""]\n')
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    commit(repo, "Change a, an empty fragment")
    assert len(check.fragment_errors(repo)) == 1


def test_a_merge_that_changes_a_plugin_itself_needs_a_fragment(repo):
    """H8: a merge's own changes (its conflict resolution or an edit made in it) are read."""
    git(repo, "checkout", "-q", "-b", "side")
    write(repo, "README.md", "side\n")
    commit(repo, "Side [no changelog]")
    git(repo, "checkout", "-q", "main")
    write(repo, "galaxy.yml", yaml.safe_dump(dict(GALAXY, version="0.3.0")))
    commit(repo, "Next version")
    git(repo, "merge", "-q", "--no-ff", "--no-commit", "side")
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed in the merge\n")
    git(repo, "add", "-A")
    git(repo, "commit", "-q", "-m", "Merge side")
    (error,) = check.fragment_errors(repo)
    assert '("Merge side") changes plugins/modules/a.py without' in error


def test_a_clean_merge_needs_nothing_of_its_own(repo):
    git(repo, "checkout", "-q", "-b", "side")
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    fragment(repo)
    commit(repo, "Change a")
    git(repo, "checkout", "-q", "main")
    write(repo, "README.md", "main\n")
    commit(repo, "Docs")
    git(repo, "merge", "-q", "--no-ff", "-m", "Merge side", "side")
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
    """CI may clone with --depth and has no remote to deepen from: where the release commit is not in the clone,
    every commit held is read but the boundary commit, whose parent is not there (one line names it)."""
    write(repo, "README.md", "one\n")
    commit(repo, "One")
    write(repo, "plugins/modules/late.py", module_source("late", "0.2.0"))
    commit(repo, "A module without a fragment")
    write(repo, "README.md", "two\n")
    two_sha = commit(repo, "Two")
    one, two = tmp_path / "one", tmp_path / "two"
    git(tmp_path, "clone", "-q", "--depth", "1", f"file://{repo}", str(one))
    assert check.fragment_errors(one) == []
    out = capsys.readouterr().out
    assert f"a shallow clone without release 0.1.0's commit: its boundary commit {two_sha[:12]} could not" in out
    # deep enough to hold the commit without a fragment after its boundary commit (One, not the release): found
    git(tmp_path, "clone", "-q", "--depth", "3", f"file://{repo}", str(two))
    assert git(two, "rev-parse", "--is-shallow-repository").strip() == "true"
    (error,) = check.fragment_errors(two)
    assert "plugins/modules/late.py" in error
    assert "since the shallow clone's boundary" in error
    assert "release commit" not in error


def test_a_shallow_clone_s_boundary_commit_is_not_the_release_commit(repo, tmp_path, capsys):
    """H1: a boundary that changes a plugin without a fragment is named as not judged; the next commit is read."""
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed\n")
    boundary = commit(repo, "Change a")
    write(repo, "plugins/modules/a.py", module_source("a", "0.1.0") + "# changed again\n")
    after = commit(repo, "Change a again")
    clone = tmp_path / "clone"
    git(tmp_path, "clone", "-q", "--depth", "2", f"file://{repo}", str(clone))
    (error,) = check.fragment_errors(clone)
    assert error.startswith(f"commit {after[:12]}")
    assert f"its boundary commit {boundary[:12]} could not be judged" in capsys.readouterr().out


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
