"""The registry: kinds declared by the packages that own them, built-ins found without a central list, plug-ins
registered before or after their kind's owner is imported, and errors that name the key and the choices."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
from geoloc import registry
from geoloc.config import ConfigError
from geoloc.launch.run import find_task

from conftest import REPO
from helpers.registry_tables import registry_copied


@pytest.fixture
def scratch(monkeypatch):
    """The registry's tables as copies, so what a test declares or registers is gone after it."""
    registry_copied(monkeypatch)


def widget(size: int = 1) -> dict:
    return {"size": size}


def test_a_plugin_may_register_before_its_kind_is_declared(scratch):
    registry.register("widget", "plain", widget)
    with pytest.raises(ValueError, match=r"component kind 'widget' is not declared; the declared kinds are \[.*'task'"):
        registry.names("widget")
    registry.declare("widget", section="task.widget")
    assert registry.names("widget") == ["plain"]
    assert registry.build("widget", {"name": "plain", "size": 3}) == {"size": 3}
    with pytest.raises(ConfigError, match=r"task.widget.sise is not an argument of .*widget; its arguments are "
                                          r"\['size'\]"):
        registry.build("widget", {"name": "plain", "sise": 3})
    with pytest.raises(ConfigError, match=r"task.widget.name='fancy' is not a known widget; choose one of \['plain'\]"):
        registry.find("widget", {"name": "fancy"})


def test_a_misspelt_kind_in_a_plugin_is_pointed_out(scratch):
    registry.declare("widget", section="widget")
    registry.register("widgit", "fancy", widget)
    with pytest.raises(ConfigError, match=re.escape("Registered under kinds nobody declares (misspelt?): "
                                                    "{'widgit': ['fancy']}")):
        registry.lookup("widget", "fancy")


def test_a_kind_is_declared_once_and_a_name_taken_once(scratch):
    registry.declare("widget", section="widget")
    registry.declare("widget", section="widget")  # its owner imported again: nothing changes
    with pytest.raises(ValueError, match="already declared for config section 'widget'"):
        registry.declare("widget", section="gadget")
    registry.register("widget", "plain", widget)
    with pytest.raises(ValueError, match=r"widget 'plain' is already registered by .*widget; pick another name"):
        registry.register("widget", "plain", lambda: None)


def test_a_kind_can_find_its_builtins_on_first_lookup(scratch):
    loads = []
    registry.declare("widget", section="widget", load=lambda: loads.append(registry.register("widget", "w", widget)))
    assert loads == []  # declaring imports nothing
    assert registry.names("widget") == ["w"] and registry.names("widget") == ["w"] and len(loads) == 1


def test_the_registry_imports_no_package_that_owns_a_kind():
    """Lookups find geoloc's built-ins through the kinds' owners; the registry itself names none of them."""
    code = "import sys, geoloc.registry; print(sorted(m for m in sys.modules if m.startswith('geoloc')))"
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "['geoloc', 'geoloc.config', 'geoloc.registry']"
    assert not re.search(r"geoloc\.(tasks|models|losses|data|datasets)", (REPO / "geoloc/registry.py").read_text()
                         .split('"""', 2)[2])  # beyond the docstring


def test_a_new_folder_under_geoloc_tasks_is_a_task(tmp_path):
    """Tasks are found, not listed: a package beside crossview/ and mmdip/ that registers itself is a task."""
    (tmp_path / "echo").mkdir()
    (tmp_path / "echo" / "__init__.py").write_text(
        "import sys\nfrom geoloc import registry\n\n\ndef train(cfg, run_dir):\n    return {}\n\n\n"
        "def evaluate(cfg, state):\n    return {}\n\n\nregistry.register('task', 'echo', sys.modules[__name__])\n")
    code = (f"import geoloc.tasks\ngeoloc.tasks.__path__.append({str(tmp_path)!r})\n"
            "from geoloc.launch.run import find_task\nfrom geoloc import registry\n"
            "print(find_task({'name': 'echo'}).__name__, registry.names('task'))")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "geoloc.tasks.echo ['crossview', 'echo', 'mmdip']"


def test_a_task_is_found_by_name_and_a_config_without_one_is_crossview():
    assert find_task({"name": "mmdip"}).__name__ == "geoloc.tasks.mmdip"
    assert find_task(None).__name__ == find_task({"name": None}).__name__ == "geoloc.tasks.crossview"
    with pytest.raises(ConfigError, match=r"task.name='mmdp' is not a known task; choose one of \['crossview', "
                                          r"(.*, )?'mmdip'"):  # (a plug-in task another test registered)
        find_task({"name": "mmdp"})


def test_every_kind_is_in_docs_extending():
    find_task({"name": "mmdip"})  # imports every task, and with them every kind's owner
    table = (REPO / "docs" / "extending.md").read_text()
    for kind, declared in registry.kinds().items():
        assert re.search(rf"^\| `{kind}` \| `{re.escape(declared.section)}", table, re.M), kind
