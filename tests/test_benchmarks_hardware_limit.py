"""The hardware's limit of a training step (`lerobot_sdp.benchmarks.hardware_limit`): FLOPs counted as
worked out by hand, rates that are rates, and the thread count left as it was."""

import torch

from lerobot_sdp.benchmarks import hardware_limit


def test_a_linear_layers_step_counts_its_three_products():
    layer = torch.nn.Linear(8, 4, bias=False)
    x = torch.randn(5, 8, requires_grad=True)
    flops = hardware_limit.step_flops(lambda: layer(x).sum().backward())
    # forward 5x8 @ 8x4: 2*5*8*4 = 320; backward: the input's gradient and the weight's, 320 each
    assert flops == 960


def test_the_conv_shape_counts_what_torch_counts():
    shape = hardware_limit.ConvShape(batch=3, channels=6, length=10, kernel=5)
    x, w = torch.randn(3, 6, 10), torch.randn(6, 6, 5)
    counted = hardware_limit.step_flops(lambda: torch.nn.functional.conv1d(x, w, padding=2))
    assert shape.flops == counted == 2 * 3 * 10 * 6 * 6 * 5


def test_throughput_measures_both_kernels_and_restores_the_threads():
    before = torch.get_num_threads()
    rate = hardware_limit.throughput(
        1, torch.float32, hardware_limit.ConvShape(2, 8, 16, 5), min_seconds=0.05
    )
    assert torch.get_num_threads() == before
    assert rate["gemm_gflops"] > 0.1 and rate["conv1d_gflops"] > 0.01
    assert rate["peak_gflops"] == max(rate["gemm_gflops"], rate["conv1d_gflops"])
