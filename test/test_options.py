"""The option table (centroiding/options.py) agrees with what each class takes and validates."""

import pytest

from lgs_wfs_ros.centroiding import ALGORITHMS, options
from lgs_wfs_ros.centroiding import _CLASSES, CMF, GridCMF, make_centroider
from lgs_wfs_ros.sensor import Sensor


def test_table_covers_every_algorithm_and_only_real_options():
    assert set(options.OPTIONS) == set(ALGORITHMS)
    for name, rows in options.OPTIONS.items():
        names = [o.name for o in rows]
        assert len(names) == len(set(names)), name
        assert set(names) <= set(_CLASSES[name]._allowed), (name, set(names) - set(_CLASSES[name]._allowed))


@pytest.mark.parametrize("algorithm", ["cog", "tcog", "wcog", "cmf", "corr", "ml"])
def test_defaults_build_and_match_the_class(algorithm):
    sensor = Sensor.paper_single("polar")
    built = options.build(algorithm, sensor)
    plain = make_centroider(algorithm, sensor)
    assert type(built) is type(plain)
    # the grid cmf records what applies to it: not the single filter's own options
    skip = set(CMF.SINGLE_DEFAULTS) - {"reference"} if isinstance(built, GridCMF) else set()
    for key, value in options.defaults(algorithm).items():
        if key in skip:
            assert key not in built.options, (algorithm, key)
        else:
            assert built.options[key] == plain.options[key], (algorithm, key)


def test_cmf_is_the_grid_of_filters_with_the_pupil_reference_and_single_otherwise():
    sensor = Sensor.paper_single("polar")
    assert isinstance(options.build("cmf", sensor), GridCMF)
    assert isinstance(options.build("cmf", sensor, {"filters": "grid"}), GridCMF)
    for given in ({"filters": "single"}, {"reference": "history"}, {"reference": "model"}):
        c = options.build("cmf", sensor, given)
        assert type(c) is CMF and c.options["filters"] == "single", given
    grid = options.build("cmf", sensor)
    assert grid.describe()["algorithm"] == "cmf"
    assert grid.describe()["options"]["filters"] == "grid"
    # what it records builds the same estimator again (replay uses the recorded options)
    again = options.build("cmf", sensor, {k: v for k, v in grid.describe()["options"].items()
                                          if k not in ("background", "read_noise_e")})
    assert isinstance(again, GridCMF) and again.options == grid.options


@pytest.mark.parametrize("given, match", [
    ({"filters": "grid", "reference": "history"}, "reference=pupil"),
    ({"linearize": False}, "linearize applies to filters=single"),
    ({"weighting": "image"}, "weighting applies to filters=single"),
    ({"filters": "single", "grid": 3}, "grid applies to filters=grid"),
    ({"reference": "model", "picks": 1}, "picks applies to filters=grid"),
])
def test_cmf_refuses_an_option_its_filters_would_ignore(given, match):
    with pytest.raises(ValueError, match=match):
        options.build("cmf", Sensor.paper_single("polar"), given)


def test_every_choice_is_accepted_by_its_class():
    """A choice the table offers but the class refuses would be a parameter that cannot be set."""
    sensor = Sensor.paper_single("polar")
    for algorithm, rows in options.OPTIONS.items():
        for opt in rows:
            for value in opt.choices:
                if (opt.name, value) == ("reference", "static"):
                    continue   # needs an image from Python; the class tests cover it
                # the single filter's own options are refused by the grid cmf (tested below)
                single = algorithm == "cmf" and opt.name in CMF.SINGLE_DEFAULTS
                options.build(algorithm, sensor, {opt.name: value,
                                                  **({"filters": "single"} if single else {})})


def test_parameters_map_to_options_with_sentinels_dropped():
    got = options.from_parameters("cmf", {"cmf.reference": "model", "cmf.background": -1.0,
                                          "cmf.history": 3, "cog.background": 2.0})
    assert got == {"reference": "model", "history": 3}


def test_an_integer_is_taken_for_a_float_and_nothing_else_is():
    opt = options.option("cmf", "dither")
    assert options.coerce(opt, 1) == 1.0 and isinstance(options.coerce(opt, 1), float)
    with pytest.raises(ValueError, match="must be float"):
        options.coerce(opt, "0.1")
    with pytest.raises(ValueError, match="must be int"):
        options.coerce(options.option("cmf", "history"), 2.5)
    with pytest.raises(ValueError, match="one of"):
        options.coerce(options.option("cmf", "reference"), "bogus")
    with pytest.raises(ValueError, match=r"must be in"):
        options.coerce(opt, 5.0)


def test_build_refuses_an_unknown_option_with_the_allowed_ones():
    with pytest.raises(ValueError, match="allowed"):
        options.build("cog", Sensor.paper_single("polar"), {"gain": "model"})
