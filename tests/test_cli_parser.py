"""The shared key=value parser: own keys, fixed keys, pass-through of training keys, one-line errors."""

import pytest

from coherent_jax.config import ConfigError, cli

KEYS = {
    "iterations": cli.Key(5, cli.int_at_least(1), "an integer >= 1", "timed iterations"),
    "budget": cli.Key(60.0, cli.positive_float, "a number > 0", "seconds"),
    "sizes": cli.Key([16], cli.int_list(1), "a list of integers >= 1", "env counts"),
    "rows": cli.Key(["a", "b"], cli.choice_list(("a", "b", "c")), "a non-empty list of a, b, c", "rows"),
    "mode": cli.Key("a", cli.choice(("a", "b")), "a or b", "mode"),
    "flag": cli.Key(False, cli.boolean, "true or false", "flag"),
    "width": cli.Key(320, cli.int_between(16, 640), "an integer in [16, 640]", "pixels"),
}


def parse(items, **kw):
    kw.setdefault("command", "the test command")
    return cli.parse_command(items, KEYS, **kw)


def test_defaults_own_keys_and_config_pass_through():
    got = parse(
        ["iterations=3", "sizes=[64,16]", "rows=[c,a]", "flag=true", "lr=1e-3", "coherent.layers=all"]
        + ["explore=coherent", "coherent.integration=mc"]
    )
    assert got.settings == {
        "iterations": 3,
        "budget": 60.0,
        "sizes": [64, 16],
        "rows": ["a", "c"],  # in the table's order
        "mode": "a",
        "flag": True,
        "width": 320,
    }
    assert got.config.lr == pytest.approx(1e-3)
    assert (got.config.coherent.layers, got.config.coherent.integration) == ("all", "mc")
    assert got.config_items == [
        "lr=1e-3",
        "coherent.layers=all",
        "explore=coherent",
        "coherent.integration=mc",
    ]


def test_fixed_keys_and_config_defaults():
    got = parse(["num_envs=4"], fixed={"algo": "sac"}, config_defaults=["env=halfcheetah", "num_envs=8"])
    assert (got.config.algo, got.config.env, got.config.num_envs) == ("sac", "halfcheetah", 4)
    with pytest.raises(ConfigError, match="'algo'.*sets it itself") as err:
        parse(["algo=ppo"], fixed={"algo": "sac"})
    assert "\n" not in str(err.value)
    varied = parse([], fixed={"explore": None, "algo": "sac"})
    assert (varied.config.algo, varied.config.explore) == ("sac", "action")  # explore keeps its default
    with pytest.raises(ConfigError, match=r"'explore'.*\(allowed: any key except algo, explore\)"):
        parse(["explore=coherent"], fixed={"explore": None, "algo": "sac"})


def test_command_without_config_refuses_config_keys():
    assert parse(["mode=b"], config=False).config is None
    with pytest.raises(ConfigError, match=r"^unknown key 'lr'; valid keys: --help lists them all$"):
        parse(["lr=0.1"], config=False)


BAD = [
    ("iterations", "malformed"),
    ("=3", "malformed"),
    ("nope=1", r"^unknown key 'nope'; valid keys: --help lists them all$"),
    ("iteration=3", r"^unknown key 'iteration' \(did you mean iterations, coherent\.integration\?\); valid"),
    ("iterations=0", r"'iterations': '0' \(allowed: an integer >= 1\)"),
    ("iterations=2.5", "'iterations'"),
    ("budget=nan", "'budget'"),
    ("budget=-1", "'budget'"),
    ("sizes=[16,0]", "'sizes'"),
    ("sizes=[16,", "'sizes'"),
    ("sizes=[]", "'sizes'"),
    ("rows=[a,z]", r"'rows'.*\(allowed: a non-empty list of a, b, c\)"),
    ("mode=c", "'mode'"),
    ("flag=maybe", "'flag'"),
    ("width=15", r"'width': '15' \(allowed: an integer in \[16, 640\]\)"),
    ("width=641", "'width'"),
    ("lr=abc", "'lr'"),
    ("policy_hidden=[64,", "'policy_hidden'.*not valid YAML"),
    ("lr={a", "'lr'.*not valid YAML"),
    ("coherent.layers=first", "'coherent.layers'"),
    ("coherent.depth=2", "unknown key 'coherent.depth'"),
]


@pytest.mark.parametrize("item,pattern", BAD)
def test_bad_items_are_one_line_config_errors(item, pattern):
    with pytest.raises(ConfigError, match=pattern) as err:
        parse([item])
    assert "\n" not in str(err.value)


def test_output_paths_checked_before_any_work(tmp_path):
    assert cli.output_file(str(tmp_path / "new" / "deeper" / "x.json")) == str(tmp_path / "new/deeper/x.json")
    assert not (tmp_path / "new").exists()  # checking creates nothing
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "a_file").write_text("keep")
    keys = {"out": cli.Key("x.json", cli.output_file, "a writable file path", "where the JSON goes")}
    for bad in (str(tmp_path), str(tmp_path / "a_file" / "x.json"), "", "/proc/x.json"):
        with pytest.raises(ConfigError, match="'out'"):
            cli.parse_command([f"out={bad}"], keys, command="c", config=False)
    assert (tmp_path / "a_file").read_text() == "keep"
    assert cli.output_dir(str(tmp_path / "plots")) == str(tmp_path / "plots")
    with pytest.raises(ValueError):
        cli.output_dir(str(tmp_path / "a_file"))


def test_help_lines_show_defaults_and_allowed():
    lines = cli.help_lines(KEYS)
    assert any(ln.strip().startswith("sizes=[16]") and "a list of integers" in ln for ln in lines)
    assert any(ln.strip().startswith("flag=false ") for ln in lines)
