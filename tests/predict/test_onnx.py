"""Which onnxruntime execution providers the engine's networks ask for (engine/predict/onnx.py)."""
import pytest

from engine.core.errors import InputError
from engine.predict.onnx import execution_providers


def test_networks_take_the_cuda_provider_only_when_onnxruntime_has_it():
    cpu, cuda = ["CPUExecutionProvider"], ["CUDAExecutionProvider", "CPUExecutionProvider"]
    assert execution_providers(cpu) == cpu and execution_providers(cuda) == cuda
    assert execution_providers(cuda, "cpu") == cpu and execution_providers(cuda, "cuda") == cuda
    for bad in (("cuda", cpu), ("tpu", cuda)):
        with pytest.raises(InputError) as err:
            execution_providers(bad[1], bad[0])
        assert err.value.field == "INTERLEAVE_ORT_DEVICE"
