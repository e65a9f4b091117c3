# SPDX-License-Identifier: BSD-3-Clause
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import real
from uwbfuse.cli import main
from uwbfuse.config import Config, RobustKernel, UwbConfig, dump_config, load_config
from uwbfuse.errors import ConfigError


def test_dump_config_round_trips(tmp_path: Path) -> None:
    """test that the dumped defaults parse back to the defaults"""
    p = tmp_path / "d.toml"
    p.write_text(dump_config())
    assert load_config(p) == Config()


def test_misspelt_key_is_named(tmp_path: Path) -> None:
    """test that an unknown key is an error naming the dotted key"""
    p = tmp_path / "bad.toml"
    p.write_text('[uwb]\nrange_feild = "r"\n')
    with pytest.raises(ConfigError, match=r"unknown config key 'uwb.range_feild'"):
        load_config(p)


def test_bad_value_is_named(tmp_path: Path) -> None:
    """test that a wrong-typed value names its key"""
    p = tmp_path / "bad.toml"
    p.write_text("[uwb]\nsigma = -1.0\n")
    with pytest.raises(ConfigError, match=r"'uwb.sigma'"):
        load_config(p)


def test_contract_example_parses(tmp_path: Path) -> None:
    """test that the contract's example config (anchors, offsets, wheel) parses"""
    p = tmp_path / "c.toml"
    p.write_text(
        """
[anchors]
A0 = [0.0, 0.0, 1.5]
A1 = [40.0, 0.0, 1.5]
[extrinsics]
tag_in_base = [0.0, 0.0, 0.3]
imu_in_base = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
[topics]
imu = "/imu"
[uwb]
anchor_field = "anchor_id"
robust_kernel = "cauchy"
[uwb.range_offset]
A0 = 0.1
[wheel]
radius = 0.1
track_width = 0.5
"""
    )
    c = load_config(p)
    assert c.anchors["A1"] == (40.0, 0.0, 1.5)
    assert c.uwb.range_offset == {"A0": 0.1}
    assert c.uwb.robust_kernel is RobustKernel.CAUCHY
    assert c.extrinsics.tag_in_base == (0.0, 0.0, 0.3)


@pytest.mark.parametrize("name", ["labyrinth", "isas-walk1", "jackal-imu-odom"])
def test_real_configs_parse(name: str) -> None:
    """test that every shipped real-data config is accepted"""
    load_config(real(f"{name}/config.toml"))


def test_cli_bad_config_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """test that a misspelt key gives exit 2 and a single stderr line"""
    p = tmp_path / "bad.toml"
    p.write_text("[graph]\nkeyframe_rat = 5\n")
    code = main(["run", str(tmp_path / "x.mcap"), "--method", "odom", "--config", str(p)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "graph.keyframe_rat" in err[0]


def test_cli_missing_config_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """test that a missing config file is a one-line error"""
    code = main(["dump-config"])
    assert code == 0
    code = main(["run", "x.mcap", "--method", "odom", "--config", str(tmp_path / "no.toml")])
    assert code == 2
    assert "config file not found" in capsys.readouterr().err


@pytest.mark.parametrize(("text", "value"), [('"auto"', "auto"), ("true", True),
                                             ("false", False)])
def test_range_scale_takes_auto_or_a_boolean(tmp_path: Path, text: str, value: object) -> None:
    """test that graph.estimate_range_scale accepts "auto", true and false"""
    p = tmp_path / "c.toml"
    p.write_text(f"[graph]\nestimate_range_scale = {text}\n")
    assert load_config(p).graph.estimate_range_scale == value


def test_bad_union_value_names_the_field_and_both_choices(tmp_path: Path) -> None:
    """test that a bad value of a union field (bool or "auto") names the field itself"""
    p = tmp_path / "bad.toml"
    p.write_text('[graph]\nestimate_range_scale = "maybe"\n')
    with pytest.raises(ConfigError, match=r"bad value for 'graph.estimate_range_scale': "
                                          r".*boolean.* or .*'auto'"):
        load_config(p)


@pytest.mark.parametrize(("text", "value"), [('"auto"', "auto"), ("20", 20.0), ("1.5", 1.5)])
def test_imu_inflation_takes_auto_or_a_positive_number(
    tmp_path: Path, text: str, value: object
) -> None:
    """test that graph.imu_noise_inflation accepts "auto" and positive numbers"""
    p = tmp_path / "c.toml"
    p.write_text(f"[graph]\nimu_noise_inflation = {text}\n")
    assert load_config(p).graph.imu_noise_inflation == value


@pytest.mark.parametrize("text", ["0", "-3", '"loose"', "nan"])
def test_bad_imu_inflation_is_named(tmp_path: Path, text: str) -> None:
    """test that a zero, negative, NaN or unknown imu_noise_inflation names the field"""
    p = tmp_path / "bad.toml"
    p.write_text(f"[graph]\nimu_noise_inflation = {text}\n")
    with pytest.raises(ConfigError, match=r"graph.imu_noise_inflation"):
        load_config(p)


def test_sections_of_earlier_releases_move_with_a_warning(tmp_path, caplog):
    """Test that `[ekf]` (read by the UKF and LKF too) loads as `[filter]` and `[wls]
    lkf_accel_psd` as `[lkf] accel_psd`, each with a deprecation warning, and that a key
    given under both names is an error."""
    import logging

    from uwbfuse.config import load_config
    from uwbfuse.errors import ConfigError

    p = tmp_path / "old.toml"
    p.write_text("[ekf]\ngating = false\n[wls]\nlkf_accel_psd = 0.7\n")
    with caplog.at_level(logging.WARNING):
        cfg = load_config(p)
    assert cfg.filter.gating is False
    assert cfg.lkf.accel_psd == 0.7
    assert "[ekf] is now [filter]" in caplog.text
    assert "[wls] lkf_accel_psd is now [lkf] accel_psd" in caplog.text
    p.write_text("[ekf]\ngating = false\n[filter]\ngating = true\n")
    with pytest.raises(ConfigError, match="given twice"):
        load_config(p)


def test_nlos_keys_of_earlier_releases_move_to_the_one_nlos_model(tmp_path, caplog):
    """Test that the graph's and wls's NLOS keys of earlier releases load into `[nlos]`
    (with a warning each) and reach the one model the graph, wls and the filters read."""
    import logging

    from uwbfuse.config import load_config
    from uwbfuse.errors import ConfigError
    from uwbfuse.nlos import NlosModel, NlosParams

    p = tmp_path / "old.toml"
    p.write_text("[graph]\nnlos_mean = 0.25\nnlos_sigma = 0.06\nnlos_slow_sigma = 0.12\n"
                 "nlos_tau = 4.0\nnlos_segment = 0.5\nnlos_rate = 0.4\nnlos_switch = 0.1\n"
                 "[wls]\nlos_std = 0.03\nnlos_mean = 0.2\nnlos_std = 0.16\nnlos_prior = 0.3\n"
                 "[wls.anchor_nlos]\nA1 = [0.02, 0.3, 0.2, 0.5]\n")
    with caplog.at_level(logging.WARNING):
        cfg = load_config(p)
    assert "[graph] nlos_mean is now [nlos] excess_mean" in caplog.text
    assert "[wls] anchor_nlos is now [nlos] anchor" in caplog.text
    m = NlosModel.from_config(cfg)
    assert (m.sigma_los, m.sigma_nlos, m.mu_nlos, m.sigma_slow, m.tau_s, m.segment_s,
            m.p_nlos, m.p_switch) == (cfg.uwb.sigma, 0.06, 0.25, 0.12, 4.0, 0.5, 0.4, 0.1)
    assert m.per_range == NlosParams(0.03, 0.2, 0.16, 0.3)
    assert m.per_anchor == {"A1": NlosParams(0.02, 0.3, 0.2, 0.5)}
    p.write_text("[graph]\nnlos_tau = 4.0\n[nlos]\ntau = 5.0\n")
    with pytest.raises(ConfigError, match="given twice"):
        load_config(p)


@pytest.mark.parametrize("kernel", [k for k in RobustKernel if k is not RobustKernel.NONE])
def test_kernel_threshold_follows_the_kernel(kernel: RobustKernel, tmp_path: Path) -> None:
    """test that an unset [uwb] kernel_threshold is the kernel's own 95 %-efficiency value
    (asymptotic efficiency under Gaussian residuals, from the weights the graph gives), not
    Huber's for every kernel, and that a set one is kept"""
    from uwbfuse.graph.noise import robust_weight

    p = tmp_path / "k.toml"
    p.write_text(f'[uwb]\nrobust_kernel = "{kernel.value}"\n')
    c = load_config(p).uwb.kernel_threshold
    e = np.linspace(-12.0, 12.0, 48001)
    de = e[1] - e[0]
    pdf = np.exp(-0.5 * e * e) / np.sqrt(2.0 * np.pi)
    psi = robust_weight(kernel, c, e) * e
    efficiency = (np.sum(np.gradient(psi, de) * pdf) * de) ** 2 / (np.sum(psi**2 * pdf) * de)
    assert efficiency == pytest.approx(0.95, abs=2e-3)
    p.write_text(f'[uwb]\nrobust_kernel = "{kernel.value}"\nkernel_threshold = 2.0\n')
    assert load_config(p).uwb.kernel_threshold == 2.0
    assert UwbConfig().kernel_threshold == 1.345  # the default kernel, Huber


def test_nlos_switch_time_reaches_the_graphs_chain(tmp_path):
    """Test that `[nlos] switch_time` (s) reaches the one NLOS model and that a
    non-positive one is a config error."""
    from uwbfuse.config import load_config
    from uwbfuse.errors import ConfigError
    from uwbfuse.nlos import NlosModel

    p = tmp_path / "c.toml"
    p.write_text("[nlos]\nswitch_time = 3.5\n")
    assert NlosModel.from_config(load_config(p)).switch_time == 3.5
    p.write_text("[nlos]\nswitch_time = 0.0\n")
    with pytest.raises(ConfigError, match="switch_time"):
        load_config(p)
