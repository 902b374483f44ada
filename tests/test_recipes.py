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


def test_shipped_recipes_and_suites_load_from_any_folder(tmp_path, monkeypatch):
    """recipes/ and suites/ ship inside the package (ddp/recipes, ddp/suites): a relative path the working
    directory lacks names the shipped copy, so build("recipes/...") works after pip install, from any folder."""
    from pathlib import Path

    from ddp.errors import RecipeError
    from ddp.recipe import load_recipe
    from ddp.shipped import locate
    from ddp.suite import load_suite

    root = Path(__file__).resolve().parents[1]
    here, _ = load_recipe(str(root / "recipes" / "quickstart.yaml"))
    monkeypatch.chdir(tmp_path)
    assert load_recipe("recipes/quickstart.yaml")[0] == here
    assert locate("recipes/quickstart.yaml").resolve() == (root / "recipes" / "quickstart.yaml").resolve()
    suite = load_suite("suites/metaworld_smoke.yaml")  # its recipes and overlays are found the same way
    assert suite.name == "metaworld_smoke" and suite.runs
    (tmp_path / "recipes").mkdir()
    (tmp_path / "recipes" / "quickstart.yaml").write_text("name: mine\n")  # the working directory's file first
    assert load_recipe("recipes/quickstart.yaml")[0] == {"name": "mine"}
    with pytest.raises(RecipeError, match="recipe file not found"):
        load_recipe("recipes/nope.yaml")
    assert locate("data/x") == Path("data/x")  # only recipes/ and suites/ are shipped
