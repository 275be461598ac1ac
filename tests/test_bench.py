"""The profile summary of experiments/bench_train.py: kernels mapped to the code they came from, and time per stage."""
import jax
import jax.numpy as jnp
import pytest

from experiments.bench_train import bench, BenchTrainConfig, hlo_sources, short_path, time_by_stage

# an HLO module's tail as XLA 0.11 prints it: a frame's parent is printed as its id + 1 (0: none)
SYNTHETIC = '''
ENTRY %main {
  ROOT %add_sqrt_fusion.2 = f32[8,3]{1,0} fusion(%p), kind=kLoop, metadata={op_name="jit(f)/sqrt" stack_frame_id=1}
}

FileNames
1 "/venv/site-packages/mujoco/mjx/_src/math.py"
2 "/venv/site-packages/mujoco/mjx/_src/smooth.py"

FunctionNames
1 "normalize"
2 "kinematics.<locals>.fn"

FileLocations
1 {file_name_id=1 function_name_id=1 line=108 end_line=108 column=3 end_column=9}
2 {file_name_id=2 function_name_id=2 line=69 end_line=69 column=5 end_column=30}

StackFrames
1 {file_location_id=1 parent_frame_id=3}
2 {file_location_id=2 parent_frame_id=0}
3 {file_location_id=1 parent_frame_id=2}
'''


def test_kernel_attributed_past_the_helpers_to_its_stage():
    rec = hlo_sources(SYNTHETIC)["add_sqrt_fusion_2"]
    assert rec["jax_op"] == "jit(f)/sqrt" and rec["shape"] == "f32[8,3]{1,0}"
    assert rec["stack"] == ["mjx/math.py:normalize:108", "mjx/smooth.py:kinematics.<locals>.fn:69"]
    assert rec["where"] == "mjx/math.py:normalize:108"          # the innermost frame
    assert rec["stage"] == "mjx/smooth.py:kinematics"           # the innermost one outside MJX's math helpers


def _inner(x):
    return jnp.sin(x) * 3.0


def _outer(x):
    return jnp.exp(_inner(x) + 1.0)


def test_compiled_program_carries_the_frames():
    """XLA's own text of a compiled function: every op of _inner's line is attributed to it (this file, its function,
    its line); a change in how XLA prints its stack-frame tables fails here rather than in a GPU profile."""
    src = hlo_sources(jax.jit(_outer).lower(jnp.ones(4)).compile().as_text())
    stages = {r["stage"] for r in src.values()}
    assert "tests/test_bench.py:_outer" in stages, src
    line = _inner.__code__.co_firstlineno + 1
    sin = [r for r in src.values() if r["jax_op"].endswith("/sin")]
    assert sin and sin[0]["where"] == f"tests/test_bench.py:_inner:{line}", src
    assert sin[0]["stack"][1] == f"tests/test_bench.py:_outer:{_outer.__code__.co_firstlineno + 1}"   # its caller


def test_short_paths_and_time_by_stage():
    assert short_path("/x/lib/python3.12/site-packages/mujoco/mjx/_src/solver.py") == "mjx/solver.py"
    assert short_path("/work/main/mjx_morph/nets/layers.py") == "mjx_morph/nets/layers.py"
    assert short_path("/x/site-packages/flax/linen/normalization.py") == "flax/linen/normalization.py"
    ops = [{"op": "a", "ms": 3.0, "share": 0.3}, {"op": "b", "ms": 5.0, "share": 0.5},
           {"op": "c", "ms": 2.0, "share": 0.2}]
    sources = {"a": {"stage": "mjx/solver.py:solve"}, "b": {"stage": "mjx/smooth.py:kinematics"},
               "c": {"stage": "mjx/solver.py:solve"}}
    rows = time_by_stage(ops, sources)
    assert [r["stage"] for r in rows] == ["mjx/solver.py:solve", "mjx/smooth.py:kinematics"]
    assert rows[0]["ms"] == pytest.approx(5.0) and rows[0]["kernels"] == 2 and rows[0]["share"] == pytest.approx(0.5)
    assert time_by_stage([{"op": "z", "ms": 1.0, "share": 1.0}], {})[0]["stage"] == "(none)"


def test_unknown_mode_is_refused():
    with pytest.raises(ValueError, match="mode='fast': expected both, update or rollout"):
        bench(BenchTrainConfig(mode="fast"))
