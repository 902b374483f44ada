"""Bad recipes and overrides give one-line errors naming the file and the dotted key."""

import textwrap

import pytest

from ddp import build
from ddp.errors import RecipeError


def write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def error_of(recipe, overrides=()):
    with pytest.raises(RecipeError) as info:
        build(recipe, overrides)
    msg = str(info.value)
    assert "\n" not in msg, msg
    return msg


@pytest.fixture
def good(tmp_path, tiny_recipe):
    import yaml

    path = tmp_path / "good.yaml"
    path.write_text(yaml.safe_dump(tiny_recipe))
    return path


def test_unknown_plugin_name_lists_closest_and_known(tmp_path, good):
    p = write(tmp_path, "r.yaml", "base: good.yaml\npolicy:\n  scheduler:\n    name: dimm\n")
    msg = error_of(p)
    assert msg.startswith(f"{p}: policy.scheduler.name: unknown scheduler 'dimm'")
    assert "did you mean 'ddim'" in msg and "known: consistency_flow, ddim, ddpm" in msg


def test_unknown_option_suggests_closest(tmp_path, good):
    p = write(tmp_path, "r.yaml", "base: good.yaml\npolicy:\n  scheduler:\n    num_inference_step: 5\n")
    msg = error_of(p)
    assert f"{p}: policy.scheduler.num_inference_step: unknown option; did you mean 'num_inference_steps'?" in msg


def test_wrong_type(tmp_path, good):
    p = write(tmp_path, "r.yaml", "base: good.yaml\ntrain:\n  batch_size: lots\n")
    msg = error_of(p)
    assert msg.startswith(f"{p}: train.batch_size: expected int, got 'lots'")


def test_wrong_type_in_plugin_list(tmp_path, good):
    p = write(tmp_path, "r.yaml", "base: good.yaml\nworld_model:\n  denoiser:\n    down_dims: [16, x]\n")
    assert f"{p}: world_model.denoiser.down_dims[1]: expected int" in error_of(p)


def test_missing_required_option(tmp_path):
    p = write(tmp_path, "r.yaml", "seed: 3\n")
    assert error_of(p) == f"{p}: name: missing required option"


def test_missing_plugin_name(tmp_path, good):
    """A section naming no plugin starts from its default one (the encoder's: dp3); a section without a
    default plugin (the data source) asks for a name."""
    import yaml

    p = tmp_path / "r.yaml"

    data = yaml.safe_load(good.read_text())
    data["encoder"] = {"out_channels": 32}
    p.write_text(yaml.safe_dump(data))
    assert build(p).resolved["encoder"]["name"] == "dp3"
    data["data"] = {"episodes": 2}
    p.write_text(yaml.safe_dump(data))
    msg = error_of(p)
    assert msg.startswith(f"{p}: data.name: missing required option 'name'") and "synthetic_reach" in msg


def test_unknown_top_level_section(tmp_path, good):
    p = write(tmp_path, "r.yaml", "base: good.yaml\npolcy: {}\n")
    assert f"{p}: polcy: unknown option; did you mean 'policy'?" in error_of(p)


def test_bad_literal_choice(tmp_path, good):
    p = write(tmp_path, "r.yaml", "base: good.yaml\npolicy:\n  scheduler:\n    prediction_type: epsilonn\n")
    msg = error_of(p)
    assert f"{p}: policy.scheduler.prediction_type: must be one of" in msg and "did you mean 'epsilon'" in msg


def test_cross_field_rule(tmp_path, good):
    p = write(tmp_path, "r.yaml", "base: good.yaml\npolicy:\n  horizon: 4\n")
    msg = error_of(p)
    assert msg.startswith(f"{p}: policy: horizon must be >= obs_steps + action_steps - 1 = 9")


def test_fewer_executed_actions_than_observed_frames_is_refused_at_build(tmp_path, good):
    """N < M built and trained; the env's frame stacking refused it only when evaluation made the env."""
    p = write(tmp_path, "r.yaml", "base: good.yaml\npolicy:\n  obs_steps: 3\n  action_steps: 2\n")
    msg = error_of(p)
    assert msg.startswith(f"{p}: policy: action_steps must be >= obs_steps = 3"), msg


def test_bad_base_path(tmp_path):
    p = write(tmp_path, "r.yaml", "base: nowhere.yaml\nname: x\n")
    msg = error_of(p)
    assert msg.startswith(f"{p}: base: base recipe") and "nowhere.yaml' not found" in msg


def test_cyclic_base(tmp_path):
    write(tmp_path, "a.yaml", "base: b.yaml\nname: a\n")
    write(tmp_path, "b.yaml", "base: a.yaml\n")
    msg = error_of(tmp_path / "a.yaml")
    assert "base: cyclic base:" in msg and "a.yaml -> " in msg


def test_malformed_yaml_has_line_number(tmp_path):
    p = write(tmp_path, "r.yaml", "name: x\npolicy:\n  horizon: [16\n  obs_steps: 2\n")
    msg = error_of(p)
    assert msg.startswith(f"{p}: malformed YAML at line 4")


def test_recipe_not_a_mapping(tmp_path):
    p = write(tmp_path, "r.yaml", "- a\n- b\n")
    assert error_of(p) == f"{p}: a recipe must be a YAML mapping, got list"


def test_recipe_file_not_found(tmp_path):
    p = tmp_path / "missing.yaml"
    assert error_of(p) == f"{p}: recipe file not found"


@pytest.mark.parametrize(
    "override, expected",
    [
        ("policy.horizon", "--set: bad override 'policy.horizon': expected key.path=value"),
        ("policy..horizon=3", "--set: bad override 'policy..horizon=3': 'policy..horizon' is not a dotted key like a.b.c "
                              "(or a.b[0].c)"),
        ("policy.horizon=[1", "--set: policy.horizon: bad override 'policy.horizon=[1': the value is not valid YAML"),
        ("name.sub=1", "--set: name.sub: cannot set 'name.sub': 'name' is 'tiny', not a mapping"),
        ("name[0]=1", "--set: name[0]: cannot set 'name[0]': 'name' is 'tiny', not a list"),
        ("policy.denoiser.down_dims[2]=64", "--set: policy.denoiser.down_dims[2]: cannot set "
         "'policy.denoiser.down_dims[2]': 'policy.denoiser.down_dims' has 2 items (indices 0..1)"),
        ("controller.subtasks[0].target=0", "--set: controller.subtasks[0].target: cannot set "
         "'controller.subtasks[0].target': the recipe does not set 'controller.subtasks' (its default list is not "
         "indexable here): set the whole list"),
        ("controller.subtasks[x].target=0", "--set: bad override 'controller.subtasks[x].target=0': "
         "'controller.subtasks[x].target' is not a dotted key like a.b.c (or a.b[0].c)"),
    ],
)
def test_bad_override_syntax(good, override, expected):
    assert error_of(good, [override]) == expected


def test_a_list_item_is_set_by_its_index(good):
    """controller.subtasks[0].target=1 (it was refused as 'not a dotted key'); errors inside it blame it."""
    from ddp.recipe import parse_override

    assert parse_override("controller.subtasks[0].trigger.chunk=3") == (
        ["controller", "subtasks", 0, "trigger", "chunk"], 3)
    two = ["controller.subtasks=[{target: 0, trigger: {name: chunk_index, chunk: 2}}, {target: null}]"]
    exp = build(good, two + ["controller.subtasks[0].trigger.chunk=5", "controller.subtasks[1].target=0"])
    subtasks = exp.resolved["controller"]["subtasks"]
    assert subtasks[0]["trigger"]["chunk"] == 5 and subtasks[1]["target"] == 0
    msg = error_of(good, two + ["controller.subtasks[0].trigger.chunk=-1"])
    assert msg.startswith("--set controller.subtasks[0].trigger.chunk=-1: controller.subtasks[0].trigger"), msg
    # an override of another item is not blamed for this one's error (the file's, or the list's override, is)
    bad_file = good.parent / "bad_item.yaml"
    bad_file.write_text("base: good.yaml\ncontroller:\n  subtasks:\n    - {target: 0, trigger: {name: chunk_index, "
                        "chunk: -1}}\n    - {target: null}\n")
    assert error_of(bad_file, ["controller.subtasks[1].target=0"]).startswith(f"{bad_file}: controller.subtasks[0]")
    bad_list = ["controller.subtasks=[{target: 0, trigger: {name: chunk_index, chunk: -1}}, {target: null}]"]
    msg = error_of(good, bad_list + ["controller.subtasks[1].target=0"])
    assert msg.startswith(f"--set {bad_list[0]}: controller.subtasks[0]"), msg


def test_override_errors_blame_the_override_not_the_file(good):
    msg = error_of(good, ["policy.scheduler.num_inference_steps=0"])
    assert msg.startswith("--set policy.scheduler.num_inference_steps=0: policy.scheduler") and "num_inference_steps" in msg
    msg = error_of(good, ["train.batch_size=4", "train.lrr=0.1"])
    assert msg.startswith("--set train.lrr=0.1: train.lrr: unknown option; did you mean 'lr'?")
    # a rule across a section's options blames the override whose option the message names, not the last one
    msg = error_of(good, ["train.batch_size=50", "train.micro_batches=4", "train.lr=1e-3"])
    assert msg.startswith("--set train.micro_batches=4: train: micro_batches"), msg
    msg = error_of(good, ["train.micro_batches=4", "train.batch_size=50", "train.lr=1e-3"])
    assert msg.startswith("--set train.batch_size=50: train:"), msg  # the last of those it names
    four = good.parent / "four.yaml"
    four.write_text("base: good.yaml\ntrain: {micro_batches: 4}\n")
    msg = error_of(four, ["train.batch_size=50", "train.lr=1e-3"])
    assert msg.startswith("--set train.batch_size=50: train:"), msg  # micro_batches from the file
    # an error in the file itself still names the file, whatever --set did elsewhere
    bad = good.parent / "bad.yaml"
    bad.write_text("base: good.yaml\ntrain: {epochz: 3}\n")
    assert error_of(bad, ["policy.horizon=16"]).startswith(f"{bad}: train.epochz: unknown option")


def test_plugin_module_that_does_not_import(tmp_path, good):
    p = write(tmp_path, "r.yaml", "base: good.yaml\nplugins: [no_such_ddp_plugin_module]\n")
    msg = error_of(p)
    assert msg.startswith(f"{p}: plugins[0]: cannot import plugin module 'no_such_ddp_plugin_module'")


def test_base_merge_rules(tmp_path, good):
    p = write(
        tmp_path, "r.yaml",
        """
        base: good.yaml
        name: child
        policy:
          denoiser:
            down_dims: [8, 16]        # lists replace
          scheduler:
            name: consistency_flow    # another part: the base's ddim options are dropped
        """,
    )
    exp = build(p, ["train.epochs=7"])
    r = exp.resolved
    assert r["name"] == "child" and r["train"]["epochs"] == 7 and r["train"]["batch_size"] == 16
    assert r["policy"]["denoiser"]["down_dims"] == [8, 16] and r["policy"]["denoiser"]["n_groups"] == 4
    assert r["policy"]["scheduler"]["name"] == "consistency_flow" and "prediction_type" not in r["policy"]["scheduler"]


def test_resolved_recipe_rebuilds_identically(tmp_path, good):
    import torch

    exp = build(good, ["policy.scheduler.num_inference_steps=5"])
    assert exp.parts["policy.scheduler"].config.num_inference_steps == 5
    dumped = exp.save_recipe(tmp_path / "resolved.yaml")
    again = build(dumped)
    assert again.to_yaml() == exp.to_yaml()
    sd1, sd2 = exp.model.state_dict(), again.model.state_dict()
    assert sd1.keys() == sd2.keys() and all(torch.equal(sd1[k], sd2[k]) for k in sd1)


def test_exponent_without_a_dot_is_a_float(tmp_path, good):
    # YAML 1.1 (PyYAML's default) reads 3e-4 as the string '3e-4'; recipes follow YAML 1.2
    p = write(tmp_path, "r.yaml", "base: good.yaml\ntrain:\n  lr: 3e-4\n  weight_decay: 1E-6\n")
    exp = build(p, ["world_model.weight=5e-1"])
    assert exp.recipe.train.lr == pytest.approx(3e-4) and exp.recipe.train.weight_decay == pytest.approx(1e-6)
    assert exp.recipe.world_model.weight == pytest.approx(0.5)
    assert error_of(good, ["train.lr=3e"]).startswith("--set train.lr=3e: train.lr: expected float, got '3e'")


def test_an_untrusted_recipe_may_not_name_code_to_import(tiny_recipe, tmp_path):
    """A recipe read from a checkpoint (not trusted) that points foundationpose's repo / module at code of its
    choosing is refused before anything is built; the user's own recipe, or --trust-plugins, may."""
    from ddp.schema import validate

    bundle = tmp_path / "bundle"
    (bundle / "evilpkg").mkdir(parents=True)
    (bundle / "evilpkg" / "__init__.py").write_text("open(__file__ + '.ran', 'w').close()\n")
    for tracker in ({"name": "foundationpose", "repo": str(bundle)}, {"name": "foundationpose", "module": "evilpkg.x"}):
        tiny_recipe["controller"] = {"tracker": tracker}
        with pytest.raises(RecipeError, match=r"controller\.tracker\.(repo|module).*names code to import.*trust"):
            validate(tiny_recipe, "<checkpoint>", import_plugins=False)
        validate(tiny_recipe, "<recipe>", import_plugins=True)  # vouched for: accepted (built only when used)
    tiny_recipe["controller"] = {"tracker": {"name": "foundationpose"}}  # defaults import nothing of the file's
    validate(tiny_recipe, "<checkpoint>", import_plugins=False)
    assert not (bundle / "evilpkg" / "__init__.py.ran").exists()


@pytest.mark.parametrize("override, message", [
    ("train.log_every_steps=0", "log_every_steps must be >= 1; got 0"),
    ("train.num_threads=-2", "num_threads must be >= 1 or null; got -2"),
    ("ema.inv_gamma=0", "inv_gamma must be > 0; got 0"),
])
def test_values_that_would_crash_mid_run_are_refused_up_front(tiny_recipe, override, message):
    with pytest.raises(RecipeError, match=message.replace(".", r"\.", 1)):
        build(tiny_recipe, [override])


@pytest.mark.parametrize("override, key, multiple", [("policy.horizon=14", "policy.horizon", 4),
                                                      ("policy.action_steps=6", "policy.action_steps", 4)])
def test_a_length_the_u_net_cannot_halve_is_refused_when_the_model_is_built(tiny_recipe, override, key, multiple):
    """It failed at the first training step, after the demos (and named the horizon for action_steps)."""
    for net in ("policy", "world_model"):
        tiny_recipe[net]["denoiser"]["down_dims"] = [16, 32, 64]  # two halvings: lengths multiple of 4
    msg = error_of(tiny_recipe, [override])
    assert f"{key}: " in msg and f"is not a multiple of {multiple}" in msg


def test_a_world_model_scheduler_of_ones_own_does_not_clip_unless_asked(tiny_recipe):
    """Latents are not in [-1, 1]: a world_model.scheduler section without clip_sample (it replaces the
    default section, which says false) took the scheduler's own default, true."""
    tiny_recipe["world_model"]["scheduler"] = {"name": "ddim", "prediction_type": "sample"}
    assert build(tiny_recipe).resolved["world_model"]["scheduler"]["clip_sample"] is False
    tiny_recipe["world_model"]["scheduler"]["clip_sample"] = True  # asked for: kept
    assert build(tiny_recipe).resolved["world_model"]["scheduler"]["clip_sample"] is True
    tiny_recipe["policy"]["scheduler"] = {"name": "ddim"}  # the policy's actions are in [-1, 1]: its default
    assert build(tiny_recipe).resolved["policy"]["scheduler"]["clip_sample"] is True


def test_null_restores_a_mapping_options_default_so_an_overlay_can_clear_its_bases(tmp_path, good):
    """An overlay could not clear eval.env set by its base ({} merges as no change, null was refused)."""
    base = write(tmp_path, "b.yaml", "base: good.yaml\neval: {env: {seed_tasks: 1}}\n")
    assert build(base).resolved["eval"]["env"] == {"seed_tasks": 1}
    top = write(tmp_path, "t.yaml", "base: b.yaml\neval: {env: null}\n")
    assert build(top).resolved["eval"]["env"] == {}
    assert build(base, ["eval.env=null"]).resolved["eval"]["env"] == {}
    # a plugin section's null is its default part; an optional one (tracker) stays off
    assert build(base, ["world_model.scheduler=null"]).resolved["world_model"]["scheduler"]["clip_sample"] is False
    assert build(base, ["controller.tracker=null"]).resolved["controller"]["tracker"] is None


def test_a_dict_recipe_resolves_its_base_from_the_working_directory():
    """build({"base": ...}) merges the base file (relative to the working directory) instead of dropping it;
    a base that does not exist is one line."""
    from ddp.recipe import load_recipe

    data, _ = load_recipe({"base": "recipes/metaworld/quickstart_ddp.yaml", "name": "mine"})
    assert data["name"] == "mine" and data["task"]["num_points"] == 128 and data["env"]["task"] == "drawer-open"
    with pytest.raises(RecipeError, match="base recipe 'recipes/none.yaml' not found"):
        load_recipe({"base": "recipes/none.yaml"})


def test_recipe_numbers_follow_yaml_1_2():
    """YAML 1.1 read seed: 010 as octal 8 and 1:30 as 90; recipes and --set read YAML 1.2 numbers."""
    from ddp.recipe import load_yaml, parse_override

    assert load_yaml("{a: 010, b: 0o10, c: 0x10, d: 1:30, e: 3e-4, f: -7}") == {
        "a": 10, "b": 8, "c": 16, "d": "1:30", "e": 3e-4, "f": -7}
    assert parse_override("seed=010") == (["seed"], 10)
    # YAML 1.1's sexagesimal floats, yes / no / on / off booleans and dates are YAML 1.2 strings
    assert load_yaml("{a: 1:30.5, b: on, c: off, d: yes, e: No, f: 2024-06-01, g: true, h: False}") == {
        "a": "1:30.5", "b": "on", "c": "off", "d": "yes", "e": "No", "f": "2024-06-01", "g": True, "h": False}
    assert parse_override("train.lr=1:30.5") == (["train", "lr"], "1:30.5")
    assert "expected bool, got 'on'" in error_of({"name": "x"}, ["train.autocast_bf16=on"])


def test_yaml_1_2_floats_only_and_malformed_numbers_are_one_line(tmp_path):
    """'--.inf' and '._' passed the float resolver, then PyYAML's constructor raised a ValueError traceback."""
    from ddp.recipe import load_yaml, parse_override

    assert load_yaml("{a: --.inf, b: ._, c: 1_000.5, d: +.inf, e: -.5, f: 1., g: 1e3}") == {
        "a": "--.inf", "b": "._", "c": "1_000.5", "d": float("inf"), "e": -0.5, "f": 1.0, "g": 1000.0}
    assert parse_override("train.lr=--.inf") == (["train", "lr"], "--.inf")
    assert "train.lr: expected float, got '--.inf'" in error_of({"name": "x"}, ["train.lr=--.inf"])


def test_a_resolved_recipe_reads_back_equal(tmp_path):
    """Strings that are numbers only in YAML 1.2 ('1e-3', '1E5', '0o17') were dumped bare and read back as
    numbers: a checkpoint's recipe with such a name or camera then failed to load."""
    from ddp.recipe import dump_yaml, load_yaml

    data = {"name": "1e-3", "a": "1E5", "b": "0o17", "c": "yes", "d": "010", "e": ".5", "f": 1e-5, "g": 3,
            "h": [1, "2", "2024-06-01"], "i": float("inf"), "j": None, "k": "true"}
    assert load_yaml(dump_yaml(data)) == data
    exp = build({"name": "1e3", "task": {"num_points": 32}, "data": {"name": "synthetic_reach"}})
    assert build(load_yaml(exp.to_yaml())).recipe.name == "1e3"


def test_setting_an_option_of_a_default_part_keeps_its_plugin(good):
    """--set policy.scheduler.num_inference_steps=5 (the CLI help's example) on a recipe that leaves the
    scheduler at its default asked for the section's 'name', blaming the recipe file."""
    import yaml

    plain = good.parent / "plain.yaml"
    recipe = yaml.safe_load(good.read_text())
    recipe["policy"].pop("scheduler", None)
    recipe.pop("controller", None)
    plain.write_text(yaml.safe_dump(recipe))
    exp = build(plain, ["policy.scheduler.num_inference_steps=5", "controller.detector.tau=2.5"])
    assert exp.resolved["policy"]["scheduler"]["name"] == "ddim"
    assert exp.resolved["policy"]["scheduler"]["num_inference_steps"] == 5
    assert exp.resolved["controller"]["detector"]["name"] == "discrepancy"
    assert exp.resolved["controller"]["detector"]["tau"] == 2.5
    msg = error_of(plain, ["data.episodes=2", "data.name=null"])  # a section with no default plugin still asks
    assert "data.name" in msg


def test_setting_a_part_s_name_drops_the_old_part_s_options(good):
    """--set policy.scheduler.name=ddpm kept the recipe's DDIM-only options (an 'unknown option' blamed on the
    valid file); options other --set's give the new part stay, in either order."""
    p = good.parent / "trailing.yaml"
    p.write_text("base: good.yaml\npolicy:\n  scheduler: {name: ddim, timestep_spacing: trailing, num_inference_steps: 2}\n")
    for order in (["policy.scheduler.name=ddpm", "policy.scheduler.num_inference_steps=7"],
                  ["policy.scheduler.num_inference_steps=7", "policy.scheduler.name=ddpm"]):
        scheduler = build(p, order).resolved["policy"]["scheduler"]
        assert scheduler["name"] == "ddpm" and scheduler["num_inference_steps"] == 7, order
    same = build(p, ["policy.scheduler.name=ddim"]).resolved["policy"]["scheduler"]
    assert same["timestep_spacing"] == "trailing" and same["num_inference_steps"] == 2  # not a swap


def test_setting_an_option_of_a_section_the_recipe_turns_off_asks_for_a_plugin(good):
    """`controller.tracker: null` with --set controller.tracker.<option> silently became the default (oracle)
    tracker; now the error asks for a name, and naming one (in either order) turns it on."""
    p = good.parent / "no_tracker.yaml"
    p.write_text("base: good.yaml\ncontroller:\n  tracker: null\n")
    msg = error_of(p, ["controller.tracker.refine=rigid"])
    assert "controller.tracker.refine" in msg and "controller.tracker.name" in msg and "null" in msg, msg
    for order in (["controller.tracker.name=pointcloud", "controller.tracker.refine=rigid"],
                  ["controller.tracker.refine=rigid", "controller.tracker.name=pointcloud"]):
        tracker = build(p, order).resolved["controller"]["tracker"]
        assert tracker["name"] == "pointcloud" and tracker["refine"] == "rigid", order
    assert build(p).resolved["controller"]["tracker"] is None


def test_setting_a_part_s_name_keeps_nested_options_other_sets_wrote():
    """A --set one level inside a part's section survives a later --set of the part's name; the old part's own
    nested options do not."""
    from ddp.recipe import apply_overrides

    data = {"policy": {"denoiser": {"name": "a", "width": 3, "blocks": {"depth": 1, "kind": "res"}}}}
    out = apply_overrides(data, ["policy.denoiser.blocks.depth=2", "policy.denoiser.name=b"])
    assert out["policy"]["denoiser"] == {"name": "b", "blocks": {"depth": 2}}
    out = apply_overrides(data, ["policy.denoiser.name=b", "policy.denoiser.blocks.depth=2"])
    assert out["policy"]["denoiser"] == {"name": "b", "blocks": {"depth": 2}}


def test_an_output_folder_may_only_fill_in_the_recipe_s_name(good):
    """`eval.output_dir: runs/{nam}` passed the recipe check and was a KeyError traceback when the run began."""
    for key in ("train.output_dir", "eval.output_dir"):
        for bad, why in (("runs/{nam}", "KeyError"), ("runs/{0}", "IndexError"), ("runs/{", "ValueError")):
            msg = error_of(good, [f"{key}={bad}"])
            assert f"output_dir '{bad}': only {{name}}" in msg and why in msg, msg
    assert build(good, ["eval.output_dir=runs/{name}/e"]).recipe.eval.output_dir == "runs/{name}/e"


def test_python_api_overrides_name_the_key_and_a_protocol_string_is_one_name(good, monkeypatch):
    """exp.make_env(typo=1) was a raw TypeError; exp.evaluate("id") split the string into letters and said
    "unknown protocol 'i'"."""
    from ddp import evaluate as evaluate_module

    exp = build(good)
    msg = str(pytest.raises(RecipeError, exp.make_env, displacment=True).value)
    assert "env.displacment" in msg and "did you mean 'displacement'" in msg, msg
    seen = []
    monkeypatch.setattr(evaluate_module, "check_protocols", lambda names, **kw: (seen.append(list(names)), 1 / 0))
    with pytest.raises(ZeroDivisionError):  # stops right after the names were checked
        exp.evaluate("id", progress=False)
    assert seen == [["id"]]
