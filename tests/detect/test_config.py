from pathlib import Path

import pytest

from torchtrack.detect.config import load_train_config, read_name_list
from torchtrack.errors import ConfigError

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.mark.parametrize("name", ["pedestrian", "vehicle"])
def test_shipped_configs_load(name):
    cfg = load_train_config(CONFIGS / f"{name}.toml")
    assert cfg.name == name and cfg.learn.n_features == 40 and cfg.learn.calibration_fraction == 0.3
    assert all(Path(p).is_absolute() for p in cfg.data.positives + cfg.data.exclude)
    for lst in cfg.data.exclude:
        assert len(read_name_list(lst)) > 10


def test_overrides_apply():
    cfg = load_train_config(CONFIGS / "vehicle.toml", {"learn.n_features": 80, "seed": 3})
    assert cfg.learn.n_features == 80 and cfg.seed == 3


def write(tmp_path, text):
    p = tmp_path / "c.toml"
    p.write_text(text)
    return p


BASE = 'window = [40, 100]\n[data]\npositives = ["p"]\nnegatives = ["n"]\n'


def test_unknown_keys_named(tmp_path):
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['n_featurs'\] in \[learn\]"):
        load_train_config(write(tmp_path, BASE + "[learn]\nn_featurs = 3\n"))
    with pytest.raises(ConfigError, match=r"\['colour'\] in \[top level\]"):
        load_train_config(write(tmp_path, "colour = 1\n" + BASE))
    with pytest.raises(ConfigError, match="unknown config key"):
        load_train_config(write(tmp_path, BASE), {"learn.nope": 1})


@pytest.mark.parametrize(
    "extra, match",
    [
        ("[learn]\nclassifier = 'tree'\n", "learn.classifier"),
        ("[learn]\ncalibration_fraction = 1.5\n", "calibration_fraction"),
        ("[learn]\ncalibration = 'beta'\n", "learn.calibration"),
        ("[mining]\nrounds = 2\n", "negative_images"),
        ("[data]\n", "not valid TOML"),
        # each value of its key's type (these reached the training as strings or NaN)
        ("[mining]\nrounds = '1'\n", r"\[mining\]: 'rounds' must be an integer, got '1'"),
        ("[learn]\nsvm_c = 'big'\n", "'svm_c' must be a number"),
        ("[learn]\nsvm_c = nan\n", "learn.svm_c must be a finite number > 0"),
        ("[learn]\ncascade_threshold = 1e308\n", "cascade_threshold must be a running margin"),
        ("[learn]\nn_features = 4.5\n", "'n_features' must be an integer"),
        # checked by the selection only after every crop's features were computed
        (
            "[learn]\nselection_bins = 0\n",
            r"learn\.selection_bins must be an integer in \[2, 256\]",
        ),
        ("[learn]\nselection_bins = 100000\n", r"learn\.selection_bins must be an integer in"),
        # counts bounded before any work (these ran for hours, out of memory, or failed only
        # when the model was written); an empty size list was silently the default sizes
        ("[mining]\nrounds = 2000000000\n", r"mining.rounds must be in \[0, 100\]"),
        (
            "[learn]\nn_estimators = 2000000000\n",
            r"n_estimators must be an integer in \[1, 100000\]",
        ),
        ("[learn]\nn_trees = 2000000000\n", r"n_trees must be an integer in \[1, 100000\]"),
        ("[features]\nsizes = []\n", r"features.sizes = \[\] names no filter size"),
        ("[features]\nn_scales = 2000000000\n", r"n_scales must be an integer in \[1, 8\]"),
        (
            "[features]\nkind = 'channels'\nboxes = 2000000000\n",
            r"features.boxes must be an integer in \[0, 1000000\]",
        ),
        (
            "[features]\nkind = 'channels'\nhaar = 2000000000\n",
            r"features.haar must be an integer in \[0, 1000000\]",
        ),
    ],
)
def test_bad_values(tmp_path, extra, match):
    with pytest.raises(ConfigError, match=match):
        load_train_config(write(tmp_path, BASE + extra))


CHANNELS = "[features]\nkind = 'channels'\n"


@pytest.mark.parametrize(
    "extra, match",
    [
        # the feature banks' own checks said 'cell must be ...', 'stride must be ...' (the Haar
        # ones only once the training ran), not the key written here
        (CHANNELS + "cell = 0", r"features\.cell must be an integer in \[1, 64\], got 0"),
        (
            CHANNELS + "cell = 3",
            r"window \[40, 100\] must be positive multiples of features\.cell 3",
        ),
        (CHANNELS + "orientations = 0", r"features\.orientations must be an integer in \[1, 18\]"),
        (CHANNELS + "norm_radius = 99", r"features\.norm_radius must be an integer in \[0, 32\]"),
        (CHANNELS + "norm_const = 0", r"features\.norm_const must be a positive number"),
        (CHANNELS + "gradient_lambda = 5", r"features\.gradient_lambda must be a number in"),
        (CHANNELS + "channels = []", r"features\.channels must be a non-empty list"),
        (CHANNELS + "channels = ['X']", r"unknown channel name 'X' in features\.channels"),
        (CHANNELS + "channels = ['L', 'L']", r"channel names in features\.channels must be"),
        (
            CHANNELS + "cells = false\nboxes = 0\nhaar = 0",
            r"features\.cells = false with features\.boxes = 0 and features\.haar = 0",
        ),
        ("[features]\nstride = 0", r"features\.stride must be an integer in \[1, 100\], got 0"),
        (
            "[features]\nmin_std = 0",
            r"features\.min_std must be a finite number in \[0\.001, 255\.0\]",
        ),
        ("[features]\nmin_std = -1", r"features\.min_std must be a finite number .*got -1"),
        ("[features]\nsizes = [6]", r"features\.sizes: filter size 6 is not a multiple of 4"),
        ("[features]\nsizes = [400]", r"features\.sizes: .* in \[4, 40\]"),
        ("[features]\nsizes = [8, 8]", r"features\.sizes must be distinct"),
        ("[features]\nn_scales = 7", r"features\.n_scales must be an integer in \[1, 4\]"),
    ],
)
def test_feature_errors_name_their_key(tmp_path, extra, match):
    with pytest.raises(ConfigError, match=match):
        load_train_config(write(tmp_path, BASE + extra))


def test_bounds_admit_their_limits(tmp_path):
    extra = "[features]\nn_scales = 4\n[learn]\nn_estimators = 100000\n"
    cfg = load_train_config(write(tmp_path, BASE + extra))
    assert cfg.features.n_scales == 4 and cfg.learn.n_estimators == 100000


def test_no_negatives_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="no negatives"):
        load_train_config(write(tmp_path, 'window = [8, 8]\n[data]\npositives = ["p"]\n'))
    with pytest.raises(ConfigError, match="does not exist"):
        load_train_config(tmp_path / "missing.toml")
    with pytest.raises(ConfigError, match="does not exist"):
        read_name_list(tmp_path / "missing.txt")


def test_binary_config_and_name_list_are_config_errors(tmp_path):
    # bytes that are not UTF-8 (were a UnicodeDecodeError traceback)
    (tmp_path / "b.toml").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ConfigError, match=r"b\.toml' is not valid TOML: not UTF-8"):
        load_train_config(tmp_path / "b.toml")
    with pytest.raises(ConfigError, match=r"name list .*b\.toml' is not a text file .*UTF-8"):
        read_name_list(tmp_path / "b.toml")


@pytest.mark.parametrize("name", ["", "x" * 257, 7])
def test_a_name_no_model_file_may_hold_is_refused_before_training(tmp_path, name):
    with pytest.raises(ConfigError, match="name must be a string of 1 to 256 characters"):
        load_train_config(write(tmp_path, BASE), {"name": name})


def test_object_region_to_window_fractions(tmp_path):
    from torchtrack.detect.config import TrainConfig

    cfg = TrainConfig(window=[128, 64])
    cfg.data.positives = ["x"]
    cfg.data.negatives = ["y"]
    cfg.data.crop_size, cfg.data.region = [160, 96], [16, 16, 64, 128]
    cfg.data.object = [32, 32, 32, 96]
    assert cfg.validate().object_box() == (0.25, 0.125, 0.5, 0.75)
    cfg.data.object = [0, 0, 96, 160]  # the whole crop is larger than the window region
    with pytest.raises(ConfigError, match=r"data\.object"):
        cfg.validate()


@pytest.mark.parametrize(
    "line, match",
    [
        ("random_negatives = 9223372036854775807", r"random_negatives must be in \[0, 10000000\]"),
        ("random_negatives = '100'", "'random_negatives' must be an integer"),
        ("exclude = '/etc/passwd'", "'exclude' must be a list"),
        ("crop_size = 'x'", "'crop_size' must be a list"),
        # a missing number was a ValueError / IndexError traceback, an extra one was ignored
        ("crop_size = [40, 100]\nregion = [0, 0, 100]", r"data\.region must be \[x, y, w, h\]"),
        ("crop_size = [40, 100]\nregion = [0, 0, 100, 40, 1]", r"data\.region must be"),
        ("crop_size = [40]\nregion = [0, 0, 100, 40]", r"data\.crop_size must be \[H, W\]"),
        ("crop_size = [40, 100, 3]\nregion = [0, 0, 100, 40]", r"data\.crop_size must be"),
        ("crop_size = [0, 100]\nregion = [0, 0, 100, 40]", r"data\.crop_size must be"),
        ("negative_max_scale = -1", "negative_max_scale must be a finite number >= "),
        ("negative_max_scale = nan", "negative_max_scale must be a finite number >= "),
        ('positives = ["p", "p"]', "data.positives names '.*/p' twice"),
        # a folder in both classes trained for minutes, then failed on the Platt slope (or, with
        # other folders beside it, gave a model whose positives were also its negatives)
        ('negatives = ["q", "p"]', "data.negatives names '.*/p', a folder of data.positives"),
        ('negative_images = ["p"]', "data.negative_images names '.*/p', a folder of data.pos"),
    ],
)
def test_bad_data_values(tmp_path, line, match):
    if line.startswith("positives"):  # in place of BASE's own
        text = BASE.replace('positives = ["p"]', line)
    elif line.startswith("negatives"):
        text = BASE.replace('negatives = ["n"]', line)
    else:
        text = BASE.replace("[data]\n", f"[data]\n{line}\n")
    with pytest.raises(ConfigError, match=match):
        load_train_config(write(tmp_path, text))


def test_target_fpr_set_for_a_haar_detector_warns(tmp_path):
    """mining.target_fpr (and margin, min_scale) apply to channel detectors only; a Haar config
    that set them trained without a word. A warning, not an error: the shipped channel configs set it and switch to
    the paper's Haar setting with features.kind = "haar"."""
    import warnings

    haar = "[features]\nkind = 'haar'\n"
    with pytest.warns(UserWarning, match=r"mining\.target_fpr = 0\.001 applies to channel-feature"):
        load_train_config(write(tmp_path, BASE + haar + "[mining]\ntarget_fpr = 1e-3\n"))
    with pytest.warns(UserWarning, match=r"mining\.target_fpr = 0\.01 applies"):
        load_train_config(write(tmp_path, BASE), {"mining.target_fpr": 0.01})
    # the other channel-only mining keys, named together
    with pytest.warns(
        UserWarning, match=r"mining\.min_scale = 0\.5, mining\.margin = -2\.0 apply to"
    ):
        load_train_config(
            write(tmp_path, BASE + haar + "[mining]\nmargin = -2.0\nmin_scale = 0.5\n")
        )
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the default value every config carries: no word
        load_train_config(write(tmp_path, BASE + haar))
        load_train_config(CONFIGS / "vehicle.toml")  # channels: it applies
        load_train_config(
            write(
                tmp_path, BASE + "[features]\nkind = 'channels'\n" + "[mining]\ntarget_fpr = 1e-3\n"
            )
        )
