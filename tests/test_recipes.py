"""Every shipped recipe validates and builds; the README lists every registered plugin."""

import re

import pytest

import ddp
from ddp import build
from conftest import RECIPES, ROOT

ALL = sorted(p for p in RECIPES.rglob("*.yaml"))


@pytest.mark.parametrize("path", ALL, ids=[str(p.relative_to(RECIPES)) for p in ALL])
def test_recipe_builds(path):
    exp = build(path)
    assert exp.model.latent_dim == 128
    assert exp.recipe.world_model.enabled == (exp.model.world_model_net is not None)


def test_paper_sizes():
    sim = build(RECIPES / "methods/ddp.yaml").parameter_counts()
    simple = build(RECIPES / "base/simple_ddp.yaml").parameter_counts()
    assert 60e6 < sim["policy"] < 70e6 and 60e6 < sim["world_model"] < 70e6
    assert simple["policy"] < simple["world_model"] < sim["world_model"]


def test_readme_plugin_table_is_complete():
    readme = (ROOT / "README.md").read_text()
    table = readme.split("<!-- plugins -->")[1].split("<!-- /plugins -->")[0]
    rows = set(re.findall(r"^\| `?(\w+)`? \| `(\w+)` \|", table, flags=re.M))
    registered = {(kind, name) for kind, names in ddp.list_plugins().items() for name in names}
    assert registered == rows
