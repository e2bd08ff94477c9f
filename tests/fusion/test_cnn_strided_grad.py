"""The cutaneous net's strided 3D convolution computes its input gradient its own way on the CPU
(``fusion.cnn._strided_input_grad``); it must be the gradient of the convolution: compared with PyTorch's own
autograd (oneDNN) and, in float64, with central finite differences."""

import pytest
import torch
from torch.nn import functional as F

from fusion.cnn import CNNClassifier, CutaneousNet, _HalvingConv3d, _strided_input_grad


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
    layer = _HalvingConv3d(c, 5)
    grad_out = torch.randn(b, 5, t - 2, (rows + 1) // 2, (cols + 1) // 2, generator=gen)
    want_x, want_w = _reference(x, layer.weight, grad_out)
    xg = x.clone().requires_grad_(True)
    out = layer(xg)
    assert _custom(out)
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


def test_net_trains_through_it():
    torch.manual_seed(0)
    net = CutaneousNet(6, (8, 8), 3)
    x = torch.randn(4, 1, 6, 8, 8)
    loss = net(x).logsumexp(1).sum()
    loss.backward()
    grads = {name: p.grad for name, p in net.named_parameters()}
    assert all(g is not None and torch.isfinite(g).all() for g in grads.values())


def _custom(out: torch.Tensor) -> bool:
    return type(out.grad_fn).__name__ == "_StridedConv3dBackward"


def test_the_cutaneous_nets_strided_layers_take_the_custom_gradient():
    net = CutaneousNet(6, (8, 8), 3)
    for layer in (net.conv1, net.conv2):
        assert _custom(layer(torch.randn(2, layer.in_channels, 8, 8, 8)))
    x = torch.randn(2, 1, 6, 8, 8, requires_grad=True)
    assert _custom(net.conv1(x))  # not a copy of the layer: the net's forward pass reaches it
    net(x).sum().backward()
    assert x.grad is not None and x.grad.shape == x.shape


def test_its_state_dict_is_a_plain_conv3ds():
    """Model files hold state dicts: the layer's entries are those of the nn.Conv3d it replaced, and load into one."""
    layer = _HalvingConv3d(2, 4)
    plain = torch.nn.Conv3d(2, 4, 3, stride=(1, 2, 2), padding=(0, 1, 1), bias=False)
    assert {k: v.shape for k, v in layer.state_dict().items()} == {k: v.shape for k, v in plain.state_dict().items()}
    plain.load_state_dict(layer.state_dict())
    x = torch.randn(2, 2, 5, 9, 8)
    assert torch.equal(layer(x), plain(x))


def test_input_gradient_with_the_weight_frozen():
    torch.manual_seed(0)
    layer = _HalvingConv3d(2, 3).requires_grad_(False)
    x = torch.randn(2, 2, 5, 7, 6, requires_grad=True)
    out = layer(x)
    assert _custom(out)
    (got,) = torch.autograd.grad(out.square().sum(), x)
    plain = x.detach().requires_grad_(True)
    (want,) = torch.autograd.grad(F.conv3d(plain, layer.weight, stride=(1, 2, 2), padding=(0, 1, 1)).square().sum(),
                                  plain)
    torch.testing.assert_close(got, want)


def test_unbatched_input_keeps_pytorchs_own_path():
    layer = _HalvingConv3d(2, 3)
    x = torch.randn(2, 5, 7, 6, requires_grad=True)
    out = layer(x)
    assert not _custom(out)
    assert torch.equal(out, F.conv3d(x, layer.weight, stride=(1, 2, 2), padding=(0, 1, 1)))
    out.sum().backward()
    assert x.grad.shape == x.shape


@pytest.mark.parametrize("weight_decay", [0.0, 1e-3])
def test_the_optimizer_is_fused(weight_decay):
    model = CNNClassifier(epochs=2, weight_decay=weight_decay, schedule="constant")
    opt, _ = model._optimizer(CutaneousNet(5, (8, 8), 3), 48, "cutaneous")
    assert type(opt) is (torch.optim.AdamW if weight_decay > 0 else torch.optim.Adam)
    assert opt.defaults["fused"] is True and not opt.defaults.get("foreach")


def test_off_the_cpu_it_is_pytorchs_own_path():
    """Any other device (a meta tensor stands in for CUDA here) takes PyTorch's convolution and its gradient."""
    layer = _HalvingConv3d(2, 3).to("meta")
    out = layer(torch.empty(2, 2, 5, 9, 8, device="meta", requires_grad=True))
    assert not _custom(out)
    assert out.shape == (2, 3, 3, 5, 4)
