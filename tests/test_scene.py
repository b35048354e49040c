"""Scene loader: every documented error class, kind defaults, CSV taxels, the chapter's scenes."""

import json
from pathlib import Path

import numpy as np
import pytest

from fusion_center.core.encoding import local_decision
from taxel_net.errors import SceneError
from taxel_net.scene import FaultSpec, load_scene, scene_to_dict
from node_sim import physics

SCENES = Path(__file__).resolve().parent.parent / "scenes"

BASE = """
[scene]
name = "t"
seed = 3
cycles = 10

[bus]
bitrate = 500000
sync_period_ms = 5.0
channels = ["a", "b"]

[kinds.R]
zeta_mv = 1.0
noise_mv = 0.2
noise_sigma_mv = 0.3
signal_mv = 4.0
pf = 0.01
pm = 0.02

[[taxels]]
node_id = 1
kind = "R"
x = 0.0
y = 0.0

[[taxels]]
node_id = 2
kind = "R"
x = 10.0
y = 0.0
zeta_mv = 2.5

[[taxels]]
node_id = 1
kind = "C"
channel = 1
x = 20.0
y = 0.0
pf = 0.03
pm = 0.04

[object]
model = "small"
x = 0.0
y = 0.0
radius = 5.0
present = [[2, 5]]

[fusion]
rules = ["additive", "llr"]
decide_with = "additive"
tuple = "pm1"

[outputs]
stages = ["fusion", "area"]
"""


def write(tmp_path, text, name="s.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def load_text(tmp_path, text):
    return load_scene(write(tmp_path, text))


def test_base_scene_loads_with_kind_defaults_merged(tmp_path):
    s = load_text(tmp_path, BASE)
    assert s.name == "t" and s.n == 3 and s.seed == 3 and s.cycles == 10
    assert s.bus.bitrate == 500000 and s.bus.channels == ("a", "b")
    t0, t1, t2 = s.taxels
    assert (t0.zeta_mv, t0.noise_mv, t0.pf) == (1.0, 0.2, 0.01)    # from [kinds.R]
    assert t1.zeta_mv == 2.5 and t1.noise_mv == 0.2                # own value over the kind's
    assert (t2.kind, t2.channel, t2.zeta_mv, t2.pf) == ("C", 1, 1.0, 0.03)  # no [kinds.C]: dataclass default
    assert s.object.present == ((2, 5),)
    assert s.fusion.tuple == "pm1" and s.stages == ("fusion", "area")
    assert s.faults == ()


def test_per_taxel_arrays_override_everything(tmp_path):
    s = load_text(tmp_path, BASE + "\n[per_taxel]\nnoise_mv = [0.5, 0.6, 0.7]\n")
    assert [t.noise_mv for t in s.taxels] == [0.5, 0.6, 0.7]


def test_same_node_id_on_two_channels_is_fine_but_not_on_one(tmp_path):
    load_text(tmp_path, BASE)  # node 1 on channel 0 and on channel 1
    bad = BASE.replace("node_id = 2", "node_id = 1")
    with pytest.raises(SceneError) as e:
        load_text(tmp_path, bad)
    assert e.value.field == "taxels[1].node_id" and e.value.value == 1
    assert "duplicate" in str(e.value) and "taxels[0].node_id" in str(e.value)


def test_faults_table(tmp_path):
    s = load_text(tmp_path, BASE + """
[[faults]]
node_id = 2
fault = "stuck"
from_cycle = 3
until_cycle = 6

[[faults]]
node_id = 1
channel = 1
fault = "silent"
from_cycle = 0
""")
    assert s.faults == (FaultSpec(node_id=2, fault="stuck", from_cycle=3, channel=0, until_cycle=6),
                        FaultSpec(node_id=1, fault="silent", from_cycle=0, channel=1, until_cycle=None))
    assert [s.faults[0].active(c) for c in (2, 3, 5, 6)] == [False, True, True, False]


def test_scene_to_dict_is_json_safe(tmp_path):
    s = load_text(tmp_path, BASE)
    d = json.loads(json.dumps(scene_to_dict(s)))
    assert d["n"] == 3 and d["name"] == "t"
    assert d["taxels"][1]["zeta_mv"] == 2.5 and d["taxels"][2]["kind"] == "C"
    assert d["object"]["present"] == [[2, 5]]
    assert d["kind_counts"] == {"R": 2, "C": 1}


# (replace this, with this) -> (field, value) named by the error
ERRORS = [
    # unknown keys at every level
    (('[scene]\n', '[scene]\ncolour = "red"\n'), "scene.colour", "red"),
    (('[bus]\n', '[bus]\nspeed = 1\n'), "bus.speed", 1),
    (('zeta_mv = 1.0\n', 'zeta_mv = 1.0\ngain = 2.0\n'), "kinds.R.gain", 2.0),
    (('zeta_mv = 2.5\n', 'zeta_mv = 2.5\ncolor = "x"\n'), "taxels[1].color", "x"),
    (('radius = 5.0\n', 'radius = 5.0\nmass = 1\n'), "object.mass", 1),
    (('tuple = "pm1"\n', 'tuple = "pm1"\ngamma = 1\n'), "fusion.gamma", 1),
    (('[outputs]\n', '[outputs]\nstray = 1\n'), "outputs.stray", 1),
    # wrong types
    (('bitrate = 500000', 'bitrate = "fast"'), "bus.bitrate", "fast"),
    (('seed = 3', 'seed = 3.5'), "scene.seed", 3.5),
    (('node_id = 2', 'node_id = "2"'), "taxels[1].node_id", "2"),
    (('rules = ["additive", "llr"]', 'rules = "additive"'), "fusion.rules", "additive"),
    (('present = [[2, 5]]', 'present = [[2, 5, 7]]'), "object.present[0]", [2, 5, 7]),
    # out of range
    (('bitrate = 500000', 'bitrate = 2000000'), "bus.bitrate", 2000000),
    (('bitrate = 500000', 'bitrate = 5000'), "bus.bitrate", 5000),
    (('sync_period_ms = 5.0', 'sync_period_ms = 0.0'), "bus.sync_period_ms", 0.0),
    (('sync_period_ms = 5.0', 'sync_period_ms = -1'), "bus.sync_period_ms", -1.0),
    (('[bus]\n', '[bus]\ntransmission_type = 0\n'), "bus.transmission_type", 0),
    (('[bus]\n', '[bus]\ntransmission_type = 241\n'), "bus.transmission_type", 241),
    (('[bus]\n', '[bus]\ntransmission_type = 253\n'), "bus.transmission_type", 253),
    (('[bus]\n', '[bus]\nsync_counter = 1\n'), "bus.sync_counter", 1),
    (('[bus]\n', '[bus]\nmode = "burst"\n'), "bus.mode", "burst"),
    (('tuple = "pm1"', 'tuple = "bool"'), "fusion.tuple", "bool"),
    (('tuple = "pm1"\n', 'tuple = "pm1"\nxi = 0.0\n'), "fusion.xi", 0.0),
    (('tuple = "pm1"\n', 'tuple = "pm1"\nalpha = 1.0\n'), "fusion.alpha", 1.0),
    (('tuple = "pm1"\n', 'tuple = "pm1"\nbeta = 1.5\n'), "fusion.beta", 1.5),
    (('tuple = "pm1"\n', 'tuple = "pm1"\np = 2.5\n'), "fusion.p", 2.5),
    (('tuple = "pm1"\n', 'tuple = "pm1"\nq = -0.1\n'), "fusion.q", -0.1),
    (('tuple = "pm1"\n', 'tuple = "pm1"\nk = 4\n'), "fusion.k", 4),
    (('pf = 0.01', 'pf = 0.0'), "kinds.R.pf", 0.0),
    (('pm = 0.04', 'pm = 1.0'), "taxels[2].pm", 1.0),
    (('zeta_mv = 2.5', 'zeta_mv = -0.5'), "taxels[1].zeta_mv", -0.5),
    (('zeta_mv = 2.5', 'zeta_mv = nan'), "taxels[1].zeta_mv", "nan"),
    (('radius = 5.0', 'radius = -1.0'), "object.radius", -1.0),
    (('present = [[2, 5]]', 'present = [[5, 5]]'), "object.present[0]", [5, 5]),
    # unknown names
    (('kind = "C"', 'kind = "Q"'), "taxels[2].kind", "Q"),
    (('[kinds.R]', '[kinds.Z]'), "kinds.Z", None),
    (('kind = "C"\n', 'kind = "C"\njaw = "middle"\n'), "taxels[2].jaw", "middle"),
    (('kind = "C"\n', 'kind = "C"\naxis = "z"\n'), "taxels[2].axis", "z"),
    (('rules = ["additive", "llr"]', 'rules = ["additive", "majority"]'), "fusion.rules[1]", "majority"),
    (('decide_with = "additive"', 'decide_with = "multiplicative"'), "fusion.decide_with", "multiplicative"),
    (('model = "small"', 'model = "cloud"'), "object.model", "cloud"),
    (('stages = ["fusion", "area"]', 'stages = ["fusion", "colour"]'), "outputs.stages[1]", "colour"),
    # node-IDs and channels
    (('node_id = 2', 'node_id = 0'), "taxels[1].node_id", 0),
    (('node_id = 2', 'node_id = 128'), "taxels[1].node_id", 128),
    (('channel = 1', 'channel = 2'), "taxels[2].channel", 2),
    (('channels = ["a", "b"]', 'channels = ["a", "a"]'), "bus.channels[1]", "a"),
    (('channels = ["a", "b"]', 'channels = ["a", ""]'), "bus.channels[1]", ""),
    (('channels = ["a", "b"]', 'channels = []'), "bus.channels", []),
    # lists of names
    (('rules = ["additive", "llr"]', 'rules = []'), "fusion.rules", []),
    (('rules = ["additive", "llr"]', 'rules = ["additive", "additive"]'), "fusion.rules[1]", "additive"),
    (('stages = ["fusion", "area"]', 'stages = ["area", "area"]'), "outputs.stages[1]", "area"),
    # missing required fields
    (('name = "t"\n', ''), "scene.name", None),
    (('tuple = "pm1"\n', ''), "fusion.tuple", None),
    (('node_id = 2\nkind = "R"\n', 'node_id = 2\n'), "taxels[1].kind", None),
    (('model = "small"\n', ''), "object.model", None),
    # cross-field
    (('x = 10.0\ny = 0.0\nzeta_mv', 'zeta_mv'), "taxels[1].x", None),          # footprint needs x, y
    (('x = 10.0\ny = 0.0\nzeta_mv', 'x = 10.0\nzeta_mv'), "taxels[1].y", None),  # x without y
    (('pf = 0.03\npm = 0.04\n', ''), "fusion.rules", ["additive", "llr"]),      # llr needs pf, pm
    (('radius = 5.0', 'radius = 5.0\nreadings_mv = [1, 2, 3]'), "object.readings_mv", [1, 2, 3]),
]


@pytest.mark.parametrize("edit, field, value", ERRORS, ids=[e[1] + "-" + str(i) for i, e in enumerate(ERRORS)])
def test_each_error_names_file_field_value(tmp_path, edit, field, value):
    old, new = edit
    assert old in BASE, old
    path = write(tmp_path, BASE.replace(old, new, 1))
    with pytest.raises(SceneError) as e:
        load_scene(path)
    err = e.value
    assert err.path == str(path) and err.field == field
    msg = str(err)
    assert msg.startswith(str(path)) and field in msg
    if value == "nan":
        assert np.isnan(err.value)
    elif value is not None:
        assert err.value == value and repr(value) in msg
    assert err.problem


@pytest.mark.parametrize("old, new, field", [
    ('kind = "C"', 'kind = 5', "taxels[2].kind"),
    ('model = "small"', 'model = true', "object.model"),
])
def test_a_choice_of_the_wrong_type_says_what_it_may_be(tmp_path, old, new, field):
    """A field that takes one of a few names, given a number: the message lists the names (it
    said only "must be a string")."""
    path = write(tmp_path, BASE.replace(old, new, 1))
    with pytest.raises(SceneError) as e:
        load_scene(path)
    assert e.value.field == field and e.value.problem.startswith("must be one of ")


def test_fault_errors(tmp_path):
    for body, field in [
        ('node_id = 9\nfault = "stuck"\nfrom_cycle = 0', "faults[0].node_id"),       # no such taxel
        ('node_id = 2\nfault = "melted"\nfrom_cycle = 0', "faults[0].fault"),
        ('node_id = 2\nfault = "stuck"\nfrom_cycle = 4\nuntil_cycle = 4', "faults[0].until_cycle"),
        ('node_id = 2\nfault = "stuck"', "faults[0].from_cycle"),
        ('node_id = 2\nfault = "stuck"\nfrom_cycle = 0\nlater = 1', "faults[0].later"),
    ]:
        with pytest.raises(SceneError) as e:
            load_text(tmp_path, BASE + "\n[[faults]]\n" + body + "\n")
        assert e.value.field == field


def test_syntax_error_and_unreadable_file(tmp_path):
    with pytest.raises(SceneError) as e:
        load_text(tmp_path, BASE + "\n[bus\n")
    assert "TOML" in str(e.value)
    missing = tmp_path / "nope.toml"
    with pytest.raises(SceneError) as e:
        load_scene(missing)
    assert e.value.path == str(missing) and "cannot read" in str(e.value)


def test_exactly_one_taxel_source(tmp_path):
    with pytest.raises(SceneError) as e:
        load_text(tmp_path, 'taxels_file = "x.csv"\n' + BASE)
    assert e.value.field == "taxels"


CSV_SCENE = """taxels_file = "data/t.csv"
[scene]
name = "csv"
[kinds.R]
zeta_mv = 1.5
[object]
model = "none"
[fusion]
tuple = "01"
"""


def csv_scene(tmp_path, csv_text):
    (tmp_path / "data").mkdir(exist_ok=True)
    (tmp_path / "data" / "t.csv").write_text(csv_text)
    return write(tmp_path, CSV_SCENE)


def test_csv_taxels_relative_to_the_scene(tmp_path):
    s = load_scene(csv_scene(tmp_path, "node_id,kind,x,y,slope,intercept\n1,R,0,0,,\n2,R,1,0,0.5,-0.1\n\n3,C,2,0,,\n"))
    assert [t.node_id for t in s.taxels] == [1, 2, 3]
    assert s.taxels[0].slope is None and s.taxels[1].slope == 0.5 and s.taxels[1].intercept == -0.1
    assert s.taxels[0].zeta_mv == 1.5 and s.taxels[2].zeta_mv == 1.0


@pytest.mark.parametrize("csv_text, field, value", [
    ("node_id,kind,colour\n1,R,red\n", "line 1, column colour", "colour"),
    ("node_id,kind\n1,R\nabc,R\n", "line 3, column node_id", "abc"),
    ("node_id,kind,x,y\n1,R,0,zero\n", "line 2, column y", "zero"),
    ("node_id,kind\n1,R\n1,C\n", "line 3, column node_id", 1),
    ("node_id,kind\n1,R\n200,C\n", "line 3, column node_id", 200),
    ("node_id,kind\n1,R\n2,X\n", "line 3, column kind", "X"),
    ("node_id,kind,zeta_mv\n1,R,-1\n", "line 2, column zeta_mv", -1.0),
    ("node_id,kind\n1,R,5\n", "line 2", ["1", "R", "5"]),
])
def test_csv_errors_name_file_line_column(tmp_path, csv_text, field, value):
    with pytest.raises(SceneError) as e:
        load_scene(csv_scene(tmp_path, csv_text))
    assert e.value.path == str(tmp_path / "data" / "t.csv")
    assert e.value.field == field and e.value.value == value
    assert str(e.value).startswith(str(tmp_path / "data" / "t.csv") + ": " + field)


def test_more_than_127_taxels_need_channels(tmp_path):
    rows = "".join(f"{i % 127 + 1},R,{i},0,{i // 127}\n" for i in range(200))
    text = "node_id,kind,x,y,channel\n" + rows
    p = csv_scene(tmp_path, text)
    with pytest.raises(SceneError) as e:  # channel 1 does not exist in the default bus
        load_scene(p)
    assert e.value.field == "line 129, column channel"
    p.write_text(CSV_SCENE.replace("[scene]", '[bus]\nchannels = ["c0", "c1"]\n[scene]'))
    # node-IDs 1..127 all taken on channel 0: none is left for the master's heartbeat
    with pytest.raises(SceneError) as e:
        load_scene(p)
    assert e.value.field == "master.node_id" and e.value.value == 127
    assert "no taxel uses" in e.value.problem and "heartbeat_ms = 0" in e.value.problem
    assert "\n" not in str(e.value)
    p.write_text(CSV_SCENE.replace("[scene]", '[bus]\nchannels = ["c0", "c1"]\n[master]\nheartbeat_ms = 0\n[scene]'))
    s = load_scene(p)
    assert s.n == 200 and {t.channel for t in s.taxels} == {0, 1} and s.master_heartbeat_ms == 0


# ---------------------------------------------------------------- the project's scenes

@pytest.mark.parametrize("path", sorted(SCENES.glob("*.toml")), ids=lambda p: p.name)
def test_every_scene_file_loads(path):
    s = load_scene(path)
    assert s.n >= 1 and s.name
    json.dumps(scene_to_dict(s))


def kind_counts(s):
    return {k: sum(t.kind == k for t in s.taxels) for k in sorted({t.kind for t in s.taxels})}


def test_matrix57_is_the_chapter_sensor():
    s = load_scene(SCENES / "matrix57.toml")
    assert kind_counts(s) == {"C": 21, "P": 4, "R": 32}      # sec 6.1
    assert [t.node_id for t in s.taxels] == list(range(1, 58))
    f = s.fusion
    # sec 6.3: beta = 0.83; the decision of sec 6.3.1 uses the negative root found with alpha = 0.473
    assert (f.xi, f.alpha, f.beta, f.tuple) == (0.003, 0.473, 0.83, "pm1")
    assert set(f.rules) == {"additive", "multiplicative", "k-of-n", "llr", "np"}
    assert (s.bus.bitrate, s.bus.sync_period_ms, s.bus.transmission_type) == (1_000_000, 10.0, 1)
    assert (s.forces.mu, s.forces.unit) == (0.3, "kgf")
    assert s.stages == ("fusion", "forces", "area", "contact_type")


@pytest.mark.parametrize("name", ["matrix57.toml", "gripper18.toml"])
def test_declared_pf_pm_match_the_simulated_detector(name):
    # pf = Q(zeta/sigma), pm = Phi((zeta - S)/sigma) for Gaussian noise (eqs 1-4); checked
    # with the error function from the standard library (independent of the scene's numbers)
    from math import erfc, sqrt

    def q(z):
        return 0.5 * erfc(z / sqrt(2))

    s = load_scene(SCENES / name)
    for t in s.taxels:
        assert t.pf == pytest.approx(q(t.zeta_mv / t.noise_sigma_mv), rel=0.05), t
        assert t.pm == pytest.approx(q((t.signal_mv - t.zeta_mv) / t.noise_sigma_mv), rel=0.05), t


def test_gripper18_is_the_chapter_gripper():
    s = load_scene(SCENES / "gripper18.toml")
    assert [t.kind for t in s.taxels] == ["LC"] * 2 + ["TBS"] * 10 + ["IR"] * 6   # fig 20 order
    f = s.fusion
    assert (f.decide_with, f.p, f.q, f.xi, f.alpha) == ("preferential", 1.0, 1.0, 0.003, 0.48)  # sec 7.2


def chapter_decisions(name):
    s = load_scene(SCENES / name)
    x = physics.sample_readings(s, 0)
    u = local_decision(x, [t.noise_mv for t in s.taxels], [t.zeta_mv for t in s.taxels], "pm1")
    return s, u


def test_gripper18_chapter_reproduces_sec_7_2_decisions():
    s, u = chapter_decisions("gripper18_chapter.toml")
    # sec 7.2: 13 present, absent taxels 4, 6, 10, 17, 18 (printed {u_i} matrix)
    printed_u = [1, 1, 1, -1, 1, -1, 1, 1, 1, -1, 1, 1, 1, 1, 1, 1, -1, -1]
    assert u.tolist() == printed_u
    assert np.flatnonzero(u == -1).tolist() == [3, 5, 9, 16, 17]


SEC62_Y = [2.3, 7.8, 0.6, 0.8, 15.6, 5.8, 2.4, 18.0, 4.3, 5.5, 4.2, 0.5, 3.7, 2.7, 5.1, 5.4, 8.8, 19.3,
           14.6, 4.4, 5.5, 2.6, 6.4, 8.8, 4.88, 17.0, 2.9, 13.4, 9.0, 5.6, 7.5, 11.7, 7.8, 3.6, 8.5, 5.69,
           6.5, 8.5, 9.5, 7.5, 6.4, 5.3, 4.3, 3.5, 2.6, 2.6, 4.4, 4.5, 5.6, 6.7, 7.8, 8.4, 9.6, 0.4, 9.5,
           4.6, 6.7]
SEC62_PRESENT = {5, 8, 18, 19, 20, 31, 33}


def test_matrix57_chapter_replays_printed_readings_and_no_zeta_gives_the_printed_cells():
    s, u = chapter_decisions("matrix57_chapter.toml")
    y = physics.sample_readings(s, 0) - np.array([t.noise_mv for t in s.taxels])
    assert y == pytest.approx(SEC62_Y, abs=1e-12)            # Y_i of sec 6.2 exactly (sigma = 0)
    kinds = [t.kind for t in s.taxels]
    # no per-kind cut-off reproduces the printed present set: for some kind an absent cell
    # reads at least as much as a present cell (then Y >= zeta cannot separate them)
    clash = [k for k in set(kinds)
             if any(SEC62_Y[i] >= min((SEC62_Y[j] for j in range(57)
                                       if kinds[j] == k and j + 1 in SEC62_PRESENT), default=np.inf)
                    for i in range(57) if kinds[i] == k and i + 1 not in SEC62_PRESENT)]
    assert clash  # e.g. R: cell 32 reads 11.7 (absent) > cell 20 4.4 (present)
    # the scene's per-kind zeta (R 12, C 17.5, P 7.5 mV): R present 5 (15.6), 8 (18.0),
    # 18 (19.3), 19 (14.6); no C reaches 17.5; P cells 31 and 40 read 7.5, cells 1 and 57 less
    assert (np.flatnonzero(u == 1) + 1).tolist() == [5, 8, 18, 19, 31, 40]


# ---------------------------------------------------------------- [master] node_id, heartbeat_ms

def test_master_node_id_and_heartbeat_defaults_and_keys(tmp_path):
    s = load_text(tmp_path, BASE)
    assert s.master.node_id == 127 and s.master.heartbeat_ms is None
    assert s.master_heartbeat_ms == s.bus.heartbeat_producer_ms == 100   # default: the bus's
    s = load_text(tmp_path, BASE + "\n[master]\nnode_id = 3\nheartbeat_ms = 250\n")
    assert (s.master.node_id, s.master_heartbeat_ms) == (3, 250)
    s = load_text(tmp_path, BASE.replace("sync_period_ms = 5.0", "sync_period_ms = 5.0\nheartbeat_producer_ms = 40"))
    assert s.master_heartbeat_ms == 40


@pytest.mark.parametrize("master,field,value,words", [
    ("node_id = 0", "master.node_id", 0, "1..127"),
    ("node_id = 128", "master.node_id", 128, "1..127"),
    ("node_id = 2", "master.node_id", 2, "channel 0"),      # taxel 2 on channel 0
    ("node_id = 1", "master.node_id", 1, "channel 0, 1"),   # node 1 on both channels
    ("heartbeat_ms = -1", "master.heartbeat_ms", -1, "0..21845"),
    ("heartbeat_ms = 21846", "master.heartbeat_ms", 21846, "0x1016"),
    ("heartbeat_ms = 1.5", "master.heartbeat_ms", 1.5, "integer"),
])
def test_master_node_id_and_heartbeat_errors_name_field_value_and_what_is_allowed(tmp_path, master, field, value,
                                                                                  words):
    with pytest.raises(SceneError) as e:
        load_text(tmp_path, BASE + f"\n[master]\n{master}\n")
    assert (e.value.field, e.value.value) == (field, value)
    assert words in e.value.problem and "\n" not in str(e.value)


def test_master_node_id_of_a_taxel_is_allowed_without_heartbeat(tmp_path):
    s = load_text(tmp_path, BASE + "\n[master]\nnode_id = 2\nheartbeat_ms = 0\n")
    assert s.master.node_id == 2 and s.master_heartbeat_ms == 0


def test_master_heartbeat_default_from_a_bus_period_too_long_for_0x1016(tmp_path):
    text = BASE.replace("sync_period_ms = 5.0", "sync_period_ms = 5.0\nheartbeat_producer_ms = 30000")
    with pytest.raises(SceneError) as e:
        load_text(tmp_path, text)
    assert (e.value.field, e.value.value) == ("master.heartbeat_ms", 30000)
    assert "default: bus.heartbeat_producer_ms" in e.value.problem
    assert load_text(tmp_path, text + "\n[master]\nheartbeat_ms = 1000\n").master_heartbeat_ms == 1000
