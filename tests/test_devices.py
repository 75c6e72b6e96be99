"""Device switches that run on every machine and act on CUDA only, and the start-up check that
EGL does not render on Mesa's software rasteriser beside a GPU."""
import pytest
import torch

from imssr._gl import gl_renderer, software_rendering_warning
from imssr.config import RunConfig, apply_overrides
from imssr.envs import make_env
from imssr.errors import ImssrError
from imssr.precision import configure_cuda, tf32_switches
from imssr.presets import make_config


def test_cuda_switches_leave_a_cpu_run_alone():
    before = (torch.backends.cudnn.benchmark, torch.backends.cuda.matmul.allow_tf32,
              torch.backends.cudnn.allow_tf32)
    configure_cuda(torch.device("cpu"), tf32="true")
    assert (torch.backends.cudnn.benchmark, torch.backends.cuda.matmul.allow_tf32,
            torch.backends.cudnn.allow_tf32) == before


def test_tf32_default_is_pytorchs_and_false_is_strict_float32():
    # PyTorch's defaults: TF32 in cuDNN convolutions, full float32 in matmuls.
    assert tf32_switches("default") == (False, True)
    assert tf32_switches("true") == (True, True) and tf32_switches("false") == (False, False)
    assert make_config("im-curl", "cartpole_swingup").agent.tf32 == "default"
    cfg = apply_overrides(make_config("curl", "cartpole_swingup"), ["agent.tf32=false"]).validate()
    assert cfg.agent.tf32 == "false"
    with pytest.raises(ImssrError, match="agent.tf32 must be one of default, true, false"):
        apply_overrides(make_config("curl", "cartpole_swingup"), ["agent.tf32=on"]).validate()
    # A config file that holds it as a JSON boolean reads as the mode of that name.
    data = make_config("curl", "cartpole_swingup").to_dict()
    data["agent"]["tf32"] = False
    assert RunConfig.from_dict(data).validate().agent.tf32 == "false"


def test_compile_is_opt_in_and_validated():
    agent = make_config("im-curl", "cartpole_swingup").agent
    assert agent.compile == "off"
    cfg = apply_overrides(make_config("curl", "cartpole_swingup"), ["agent.compile=reduce-overhead", "agent.tf32=true"])
    assert cfg.validate().agent.compile == "reduce-overhead" and cfg.agent.tf32 == "true"
    with pytest.raises(ImssrError, match="agent.compile must be one of off, default, reduce-overhead"):
        apply_overrides(make_config("curl", "cartpole_swingup"), ["agent.compile=fast"]).validate()


def test_software_rendering_beside_a_gpu_is_one_line_with_the_fix():
    line = software_rendering_warning("egl", "llvmpipe (LLVM 15.0.6, 256 bits)", gpu=True)
    assert line.startswith("imssr: warning: ") and "\n" not in line and "10_nvidia.json" in line
    assert software_rendering_warning("egl", "llvmpipe (LLVM 15.0.6, 256 bits)", gpu=False) is None
    assert software_rendering_warning("egl", "NVIDIA H100 80GB HBM3/PCIe/SSE2", gpu=True) is None
    assert software_rendering_warning("osmesa", "llvmpipe (LLVM 15.0.6, 256 bits)", gpu=True) is None
    assert software_rendering_warning("egl", None, gpu=True) is None


def test_the_renderer_of_a_real_env_is_read():
    env = make_env("cartpole_swingup", seed=0, image_size=32)
    try:
        env.reset(seed=0)
        renderer = gl_renderer(env.physics)
    finally:
        env.close()
    assert isinstance(renderer, str) and renderer
