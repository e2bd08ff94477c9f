"""The cutaneous net's strided 3D convolution computes its input gradient its own way on the CPU
(``fusion.cnn._strided_input_grad``); it must be the gradient of the convolution: compared with PyTorch's own
autograd (oneDNN) and, in float64, with central finite differences."""

import pytest
import torch
from torch.nn import functional as F

from fusion.cnn import CNNClassifier, CutaneousNet, _conv, _strided_input_grad


def _reference(x: torch.Tensor, weight: torch.Tensor, grad_out: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    x = x.detach().requires_grad_(True)
    weight = weight.detach().requires_grad_(True)
    out = F.conv3d(x, weight, stride=(1, 2, 2), padding=(0, 1, 1))
    return torch.autograd.grad(out, (x, weight), grad_out)


@pytest.mark.parametrize("shape", [(2, 3, 7, 8, 8), (2, 1, 5, 5, 7), (1, 2, 4, 1, 2), (3, 4, 6, 9, 4), (2, 8, 27, 16, 16)])
def test_gradients_equal_autograd(shape):
    gen = torch.Generator().manual_seed(sum(shape))
    b, c, t, rows, cols = shape
    x = torch.randn(shape, generator=gen)
    layer = torch.nn.Conv3d(c, 5, 3, stride=(1, 2, 2), padding=(0, 1, 1), bias=False)
    grad_out = torch.randn(b, 5, t - 2, (rows + 1) // 2, (cols + 1) // 2, generator=gen)
    want_x, want_w = _reference(x, layer.weight, grad_out)
    xg = x.clone().requires_grad_(True)
    out = _conv(layer, xg)
    assert torch.equal(out, F.conv3d(x, layer.weight, stride=(1, 2, 2), padding=(0, 1, 1)))  # the forward untouched
    got_x, got_w = torch.autograd.grad(out, (xg, layer.weight), grad_out)
    assert got_x.shape == x.shape
    torch.testing.assert_close(got_x, want_x, rtol=1e-5, atol=1e-5 * float(want_x.abs().max()))
    assert torch.equal(got_w, want_w)  # PyTorch's own weight gradient


def test_input_gradient_matches_finite_differences():
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(1, 2, 5, 5, 6, generator=gen, dtype=torch.float64)
    weight = torch.randn(3, 2, 3, 3, 3, generator=gen, dtype=torch.float64)
    grad_out = torch.randn(1, 3, 3, 3, 3, generator=gen, dtype=torch.float64)

    def objective(v: torch.Tensor) -> float:
        return float((F.conv3d(v, weight, stride=(1, 2, 2), padding=(0, 1, 1)) * grad_out).sum())

    got = _strided_input_grad(grad_out, weight, 5, 6)
    eps = 1e-6
    for index in [(0, 0, 0, 0, 0), (0, 1, 2, 3, 4), (0, 0, 4, 4, 5), (0, 1, 1, 2, 1), (0, 0, 3, 1, 3)]:
        up, down = x.clone(), x.clone()
        up[index] += eps
        down[index] -= eps
        assert float(got[index]) == pytest.approx((objective(up) - objective(down)) / (2 * eps), rel=1e-6, abs=1e-8)


def test_net_trains_through_it_and_other_layers_keep_pytorchs_path():
    torch.manual_seed(0)
    net = CutaneousNet(6, (8, 8), 3)
    x = torch.randn(4, 1, 6, 8, 8)
    loss = net(x).logsumexp(1).sum()
    loss.backward()
    grads = {name: p.grad for name, p in net.named_parameters()}
    assert all(g is not None and torch.isfinite(g).all() for g in grads.values())
    plain = torch.nn.Conv3d(1, 2, 3, stride=1, padding=1, bias=False)
    v = torch.randn(1, 1, 4, 4, 4)
    assert torch.equal(_conv(plain, v), plain(v))  # not the strided layout: PyTorch's layer as is


def _custom(out: torch.Tensor) -> bool:
    return type(out.grad_fn).__name__ == "_StridedConv3dBackward"


def test_the_cutaneous_nets_strided_layers_take_the_custom_gradient():
    net = CutaneousNet(6, (8, 8), 3)
    for layer in (net.conv1, net.conv2):
        assert _custom(_conv(layer, torch.randn(2, layer.in_channels, 8, 8, 8)))


def test_input_gradient_with_the_weight_frozen():
    torch.manual_seed(0)
    layer = torch.nn.Conv3d(2, 3, 3, stride=(1, 2, 2), padding=(0, 1, 1), bias=False).requires_grad_(False)
    x = torch.randn(2, 2, 5, 7, 6, requires_grad=True)
    (got,) = torch.autograd.grad(_conv(layer, x).square().sum(), x)
    plain = x.detach().requires_grad_(True)
    (want,) = torch.autograd.grad(layer(plain).square().sum(), plain)
    torch.testing.assert_close(got, want)


@pytest.mark.parametrize("options", [{"stride": 1, "padding": (0, 1, 1)}, {"stride": (1, 2, 1), "padding": (0, 1, 1)},
                                     {"stride": (1, 2, 2), "padding": (1, 1, 1)}, {"stride": (1, 2, 2), "padding": 0},
                                     {"kernel_size": (1, 3, 3), "stride": (1, 2, 2), "padding": (0, 1, 1)},
                                     {"stride": (1, 2, 2), "padding": (0, 1, 1), "dilation": (1, 2, 2)},
                                     {"stride": (1, 2, 2), "padding": (0, 1, 1), "groups": 2},
                                     {"stride": (1, 2, 2), "padding": (0, 1, 1), "bias": True}])
def test_other_conv3d_layouts_keep_pytorchs_own_path(options):
    torch.manual_seed(0)
    layer = torch.nn.Conv3d(2, 4, **{"kernel_size": 3, "bias": False, **options})
    x = torch.randn(2, 2, 5, 9, 8, requires_grad=True)
    out = _conv(layer, x)
    assert not _custom(out)
    plain = x.detach().requires_grad_(True)
    want = layer(plain)
    assert torch.equal(out, want)
    grad = torch.randn_like(want)
    for a, b in zip(torch.autograd.grad(out, (x, layer.weight), grad),
                    torch.autograd.grad(want, (plain, layer.weight), grad), strict=True):
        assert torch.equal(a, b)


def test_unbatched_input_keeps_pytorchs_own_path():
    layer = torch.nn.Conv3d(2, 3, 3, stride=(1, 2, 2), padding=(0, 1, 1), bias=False)
    x = torch.randn(2, 5, 7, 6, requires_grad=True)
    out = _conv(layer, x)
    assert not _custom(out)
    out.sum().backward()
    assert x.grad.shape == x.shape


@pytest.mark.parametrize("weight_decay", [0.0, 1e-3])
def test_the_optimizer_is_fused(weight_decay):
    model = CNNClassifier(epochs=2, weight_decay=weight_decay, schedule="constant")
    opt, _ = model._optimizer(CutaneousNet(5, (8, 8), 3), 48, "cutaneous")
    assert type(opt) is (torch.optim.AdamW if weight_decay > 0 else torch.optim.Adam)
    assert opt.defaults["fused"] is True and not opt.defaults.get("foreach")
