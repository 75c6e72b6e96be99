"""Device switches that run on every machine and act on CUDA only, and the start-up check that
EGL does not render on Mesa's software rasteriser beside a GPU."""
import subprocess
import sys

import pytest
import torch

from imssr._gl import (EGL_PINNED_VARIABLE, egl_device_error, egl_device_id, egl_vendor_hint, gl_renderer,
                       pin_egl_device, software_rendering_warning, unpin_refused_egl_device)
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
    cfg = apply_overrides(make_config("curl", "cartpole_swingup"), ["agent.compile=max-autotune", "agent.tf32=true"])
    assert cfg.validate().agent.compile == "max-autotune" and cfg.agent.tf32 == "true"
    with pytest.raises(ImssrError, match="agent.compile must be one of off, default, max-autotune$"):
        apply_overrides(make_config("curl", "cartpole_swingup"), ["agent.compile=fast"]).validate()
    with pytest.raises(ImssrError, match="agent.compile=reduce-overhead is retired: CUDA graphs of whole agent "
                                         "steps are agent.cuda_graphs=true"):
        apply_overrides(make_config("curl", "cartpole_swingup"), ["agent.compile=reduce-overhead"]).validate()


def test_software_rendering_beside_a_gpu_is_one_line_with_the_fix():
    line = software_rendering_warning("egl", "llvmpipe (LLVM 15.0.6, 256 bits)", gpu=True)
    assert line.startswith("imssr: warning: ") and "\n" not in line and "10_nvidia.json" in line
    assert software_rendering_warning("egl", "llvmpipe (LLVM 15.0.6, 256 bits)", gpu=False) is None
    assert software_rendering_warning("egl", "NVIDIA H100 80GB HBM3/PCIe/SSE2", gpu=True) is None
    assert software_rendering_warning("osmesa", "llvmpipe (LLVM 15.0.6, 256 bits)", gpu=True) is None
    assert software_rendering_warning("egl", None, gpu=True) is None


def test_egl_renders_on_the_runs_gpu():
    # No CUDA_VISIBLE_DEVICES: torch's numbering is the machine's.
    assert egl_device_id(0, None) == "0" and egl_device_id(2, None) == "2"
    # Ray or SLURM gave the run GPUs 3 and 5: cuda:0 is the machine's GPU 3, cuda:1 its GPU 5.
    assert egl_device_id(0, "3,5") == "3" and egl_device_id(1, " 3, 5") == "5"
    # A GPU named by UUID or a MIG slice, an index past the list, or no GPU visible: EGL picks.
    for visible, index in (("GPU-8f1c2d3e-aaaa", 0), ("MIG-1234", 0), ("3", 1), ("", 0)):
        assert egl_device_id(index, visible) is None
    environ = {"MUJOCO_GL": "egl", "CUDA_VISIBLE_DEVICES": "2,7"}
    assert pin_egl_device(1, environ, modules={}) == "7" and environ["MUJOCO_EGL_DEVICE_ID"] == "7"
    # Too late once dm_control's EGL renderer is loaded: it opened its display then.
    late = {"MUJOCO_GL": "egl"}
    assert pin_egl_device(0, late, modules={"dm_control._render.pyopengl.egl_renderer": None}) is None
    assert "MUJOCO_EGL_DEVICE_ID" not in late
    # The user's own choice stands; other backends and CPU runs are left alone.
    mine = {"MUJOCO_GL": "egl", "MUJOCO_EGL_DEVICE_ID": "1"}
    assert pin_egl_device(0, mine, modules={}) is None and mine["MUJOCO_EGL_DEVICE_ID"] == "1"
    for environ in ({"MUJOCO_GL": "osmesa"}, {"MUJOCO_GL": "egl"}):
        assert pin_egl_device(None if environ["MUJOCO_GL"] == "egl" else 0, environ, modules={}) is None
        assert "MUJOCO_EGL_DEVICE_ID" not in environ


REFUSED = "MUJOCO_EGL_DEVICE_ID must be an integer between 0 and 0 (inclusive), got 3."
"""dm_control's error when EGL lists fewer devices than the index (cgroup device limits)."""


def test_an_egl_device_imssr_guessed_and_egl_refused_is_dropped():
    environ = {"MUJOCO_GL": "egl", "CUDA_VISIBLE_DEVICES": "3"}
    assert pin_egl_device(0, environ, modules={}) == "3" and environ[EGL_PINNED_VARIABLE] == "3"
    # Another failure leaves the pin alone.
    assert unpin_refused_egl_device("Cannot initialize a headless EGL display.", environ) is None
    assert environ["MUJOCO_EGL_DEVICE_ID"] == "3"
    assert unpin_refused_egl_device(REFUSED, environ) == "3"
    assert "MUJOCO_EGL_DEVICE_ID" not in environ and EGL_PINNED_VARIABLE not in environ
    # The user's own value stands, even beside a stale marker, and its error says whose it is.
    for mine in ({"MUJOCO_EGL_DEVICE_ID": "3"}, {"MUJOCO_EGL_DEVICE_ID": "3", EGL_PINNED_VARIABLE: "1"}):
        assert unpin_refused_egl_device(REFUSED, mine) is None and mine["MUJOCO_EGL_DEVICE_ID"] == "3"
        message = egl_device_error(REFUSED, mine)
        assert message.startswith("MUJOCO_EGL_DEVICE_ID=3 (a value set outside imssr)")
        assert "set MUJOCO_EGL_DEVICE_ID=0" in message and "\n" not in message
    ours = {"MUJOCO_EGL_DEVICE_ID": "3", EGL_PINNED_VARIABLE: "3"}
    assert egl_device_error(REFUSED, ours).startswith("MUJOCO_EGL_DEVICE_ID=3 (imssr set it from the run's GPU)")
    assert egl_device_error("Cannot initialize a headless EGL display.", ours) is None


def test_a_task_name_resolves_before_the_gpu_is_known():
    # dm_control opens its EGL display when imported: resolving a task must not import it.
    code = ("import sys; from imssr.presets import make_config; make_config('curl', 'walker_walk'); "
            "print(any(m.startswith('dm_control') for m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_the_missing_egl_names_nvidias_package_on_a_gpu_machine():
    assert "libnvidia-gl-<driver version>" in egl_vendor_hint(True) and "libegl-nvidia0" in egl_vendor_hint(True)
    assert "libgl1-mesa-dri" in egl_vendor_hint(False) and "nvidia" not in egl_vendor_hint(False).lower()
    assert egl_vendor_hint(True) in software_rendering_warning("egl", "llvmpipe", gpu=True)


def test_the_renderer_of_a_real_env_is_read():
    env = make_env("cartpole_swingup", seed=0, image_size=32)
    try:
        env.reset(seed=0)
        renderer = gl_renderer(env.physics)
    finally:
        env.close()
    assert isinstance(renderer, str) and renderer
