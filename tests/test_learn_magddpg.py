"""MAGDDPG update rules: inverting gradients, the multi-agent actor gradient, soft target updates."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from learn.magddpg import MAGDDPG, invert_gradients, soft_update  # noqa: E402
from learn.networks import ACTOR_OUT_INIT, CRITIC_OUT_INIT, Actor, Critic  # noqa: E402


def test_invert_gradients_matches_hand_computation():
    """Inside [0, 1] the gradient is scaled towards the bound it heads for; beyond a bound it points back."""
    a = torch.tensor([0.25, 0.25, 0.9, 0.9, 1.5, -0.5, 1.5, -0.5])
    g = torch.tensor([2.0, -2.0, 1.0, -1.0, 1.0, -1.0, -1.0, 1.0])
    # increase: g * (1 - a); decrease: g * (a - 0)
    want = torch.tensor([2.0 * 0.75, -2.0 * 0.25, 1.0 * 0.1, -1.0 * 0.9,
                         1.0 * -0.5,  # above the top, pushed up: inverted (points down)
                         -1.0 * -0.5,  # below the bottom, pushed down: inverted (points up)
                         -1.0 * 1.5,  # above the top, pushed down: kept (and amplified)
                         1.0 * 1.5])  # below the bottom, pushed up: kept
    torch.testing.assert_close(invert_gradients(g, a), want)


def test_invert_gradients_other_bounds():
    """The rule uses (a_max - a)/(a_max - a_min) and (a - a_min)/(a_max - a_min) for any bounds."""
    a = torch.tensor([0.0, 0.0])
    g = torch.tensor([3.0, -3.0])
    torch.testing.assert_close(invert_gradients(g, a, a_min=-1.0, a_max=3.0),
                               torch.tensor([3.0 * 3.0 / 4.0, -3.0 * 1.0 / 4.0]))


def _agent(M=3, hist=5, S=4):
    torch.manual_seed(0)
    return MAGDDPG(hist, S, M, (6,), (8, 8), gamma=0.9, tau=0.1, lr_actor=1e-3, lr_critic=1e-3)


def test_actor_gradient_sums_over_agents():
    """The actor step's gradient is (1/N) Σ_j Σ_i J_μ(h_j^i)ᵀ invert(∇_{a^i} Q), checked agent by agent with autograd."""
    N, M, H, S = 4, 3, 5, 4
    ag = _agent(M, H, S)
    with torch.no_grad():  # make the actor's outputs land on both sides of the bounds
        ag.actor.net[-1].bias.copy_(torch.tensor([0.6, 0.3]))
        ag.actor.net[-1].weight.mul_(300.0)
    gen = torch.Generator().manual_seed(1)
    s = torch.rand(N, S, generator=gen)
    h = torch.rand(N, M, H, generator=gen)
    params = list(ag.actor.parameters())

    # reference: one robot at a time, Q's gradient wrt that robot's action, inverted, then a VJP
    a = ag.actor(h).detach()  # (N, M, 2)
    assert (a > 1).any() or (a < 0).any(), "test case should exercise the inverted branch"
    want = [torch.zeros_like(p) for p in params]
    for j in range(N):
        for i in range(M):
            a_ji = a[j:j + 1].clone().requires_grad_(True)
            (dq,) = torch.autograd.grad(ag.critic(s[j:j + 1], a_ji).sum(), a_ji)
            g = invert_gradients(dq[0, i], a[j, i])  # (2,)
            out = ag.actor(h[j, i])  # (2,) this robot's action, graph to θ^μ
            grads = torch.autograd.grad(out, params, grad_outputs=-g / N)
            want = [w + gr for w, gr in zip(want, grads)]

    # the implementation: capture the gradient the optimiser sees
    seen = {}
    orig_step = ag.actor_opt.step
    ag.actor_opt.step = lambda: seen.update(grads=[p.grad.clone() for p in params])
    ag.actor_step(s, h)
    ag.actor_opt.step = orig_step
    for w, got in zip(want, seen["grads"]):
        torch.testing.assert_close(got, w, rtol=1e-5, atol=1e-7)


def test_actor_gradient_without_inversion_is_ddpg_chain_rule():
    """With every action strictly inside (0, 1) and far from the bounds, the step follows -∇θ mean_j Q(s_j, μ(h_j)) up to the inversion factors."""
    N, M, H, S = 5, 2, 5, 4
    ag = _agent(M, H, S)
    with torch.no_grad():
        ag.actor.net[-1].bias.fill_(0.5)  # outputs ≈ 0.5: factors ≈ 0.5 for both directions
        ag.actor.net[-1].weight.zero_()
    s, h = torch.rand(N, S), torch.rand(N, M, H)
    params = list(ag.actor.parameters())
    q = ag.critic(s, ag.actor(h)).mean()
    want = torch.autograd.grad(-q, params)
    seen = {}
    ag.actor_opt.step = lambda: seen.update(grads=[p.grad.clone() for p in params])
    ag.actor_step(s, h)
    for w, got in zip(want, seen["grads"]):
        torch.testing.assert_close(got, 0.5 * w, rtol=1e-5, atol=1e-8)


def test_soft_update():
    """θ' ← τθ + (1 − τ)θ' for every parameter; τ = 1 copies."""
    torch.manual_seed(0)
    src, dst = Critic(3, 2, (4,)), Critic(3, 2, (4,))
    before = [p.detach().clone() for p in dst.parameters()]
    soft_update(dst, src, 0.25)
    for b, s, d in zip(before, src.parameters(), dst.parameters()):
        torch.testing.assert_close(d, 0.25 * s.detach() + 0.75 * b)
    soft_update(dst, src, 1.0)
    for s, d in zip(src.parameters(), dst.parameters()):
        torch.testing.assert_close(d, s.detach())


def test_update_moves_targets_by_tau():
    """One update changes the target networks by exactly τ times the gap to the learned networks."""
    from learn.replay import Batch

    ag = _agent(2, 5, 4)
    rng = np.random.default_rng(0)
    f = lambda *s: rng.random(s, dtype=np.float32)  # noqa: E731
    batch = Batch(f(8, 4), f(8, 2, 5), f(8, 2, 2), f(8), f(8, 4), f(8, 2, 5))
    tgt_before = [p.clone() for p in ag.critic_target.parameters()]
    ag.update(batch)
    for tb, t, p in zip(tgt_before, ag.critic_target.parameters(), ag.critic.parameters()):
        torch.testing.assert_close(t, tb + 0.1 * (p.detach() - tb))


def test_initialisation_ranges():
    """Hidden layers within ±1/√f, actor output within ±3e-3, critic output within ±3e-4 (thesis §4.3.1)."""
    torch.manual_seed(0)
    actor, critic = Actor(40, (16, 8)), Critic(6, 2, (32, 16))
    lin = [m for m in actor.net if isinstance(m, torch.nn.Linear)]
    assert lin[0].weight.abs().max() <= 1 / np.sqrt(40) and lin[0].weight.abs().max() > 0.5 / np.sqrt(40)
    assert lin[1].bias.abs().max() <= 1 / np.sqrt(16)
    assert lin[-1].weight.abs().max() <= ACTOR_OUT_INIT and lin[-1].bias.abs().max() <= ACTOR_OUT_INIT
    clin = [m for m in critic.net if isinstance(m, torch.nn.Linear)]
    assert clin[0].weight.shape == (32, 6 + 4)
    assert clin[-1].weight.abs().max() <= CRITIC_OUT_INIT


def test_actor_layers_export_order():
    """Actor.layers() gives (out, in) weights, ELU hidden and identity output, that reproduce the forward pass."""
    torch.manual_seed(0)
    actor = Actor(12, (5, 4))
    layers = actor.layers()
    assert [w.shape for w, _, _ in layers] == [(5, 12), (4, 5), (2, 4)]
    assert [a for _, _, a in layers] == ["elu", "elu", "identity"]
    x = np.random.default_rng(0).random((3, 12)).astype(np.float32)
    y = x
    for w, b, a in layers:
        y = y @ w.T + b
        if a == "elu":
            y = np.where(y > 0, y, np.expm1(y))
    np.testing.assert_allclose(y, actor(torch.from_numpy(x)).detach().numpy(), rtol=1e-5, atol=1e-6)


def _actor_grads(agent, part, rows, sel):
    """The gradient the actor optimiser sees for one part, with the robot subset forced to ``sel``."""
    seen = {}
    agent.robot_subset = lambda n, m: sel
    agent.actor_opt.step = lambda: seen.update(g=[p.grad.clone() for p in agent.actor.parameters()])
    agent.actor_step_parts([(part, False)], [rows], len(part))
    return seen["g"]


@pytest.mark.parametrize("kind", ["mlp", "gru"])
def test_actor_objective_on_robot_subsets_is_unbiased(kind):
    """With actor_robots = K the gradient from K robots, scaled by M/K, averages over a partition of the robots
    to the full gradient (MLP transitions and GRU windows)."""
    from learn.ddpg import Rows
    from learn.magrdpg import MAGRDPG
    from learn.replay import Batch, Windows
    N, M, S, H = 3, 4, 2 + 3 * 4, 5
    gen = torch.Generator().manual_seed(4)
    torch.manual_seed(5)
    if kind == "mlp":
        agent = MAGDDPG(H, S, M, (6,), (8,), 0.9, 0.1, 1e-3, 1e-3, actor_robots=2)
        part = Batch(s=torch.rand(N, S, generator=gen), h=torch.rand(N, M, H, generator=gen), a=None, r=None,
                     s2=None, h2=None)
        rows = Rows(s=part.s, a=None, r=None, s2=None)
    else:
        agent = MAGRDPG(H, S, M, 6, (8,), 0.9, 0.1, 1e-3, 1e-3, burn_in=2, unroll=3, actor_robots=2)
        U = 3
        part = Windows(x=torch.rand(N, M, 2 + U + 1, H, generator=gen), off=torch.tensor([0, 1, 2]),
                       s=torch.rand(N, U, S, generator=gen), a=torch.rand(N, U, M, 2, generator=gen),
                       r=torch.rand(N, U, generator=gen), s2=torch.rand(N, U, S, generator=gen))
        rows = agent.rows(part)
    with torch.no_grad():  # outputs on both sides of the bounds: the inverting branch is exercised too
        out = agent.actor.net[-1] if kind == "mlp" else agent.actor.out
        out.weight.mul_(300.0)
        out.bias.fill_(0.5)
    full = _actor_grads(agent, part, rows, None)
    first = _actor_grads(agent, part, rows, torch.tensor([[0, 1]] * N))
    second = _actor_grads(agent, part, rows, torch.tensor([[2, 3]] * N))
    for f, a, b in zip(full, first, second):
        torch.testing.assert_close((a + b) / 2, f, rtol=1e-4, atol=1e-6)
    assert any(not torch.allclose(a, f) for a, f in zip(first, full))  # a subset alone is not the full gradient


@pytest.mark.parametrize("kind", ["mlp", "gru"])
def test_actor_others_from_the_replay(kind):
    """actor_others='replay': Q sees the chosen robot's current action and the other robots' replayed ones."""
    from learn.magrdpg import MAGRDPG
    from learn.replay import Batch, Windows
    N, M, S, H, U = 3, 4, 2 + 3 * 4, 5, 3
    gen = torch.Generator().manual_seed(6)
    torch.manual_seed(7)
    if kind == "mlp":
        agent = MAGDDPG(H, S, M, (6,), (8,), 0.9, 0.1, 1e-3, 1e-3, actor_robots=1, actor_others="replay")
        part = Batch(s=torch.rand(N, S, generator=gen), h=torch.rand(N, M, H, generator=gen),
                     a=torch.rand(N, M, 2, generator=gen), r=torch.rand(N, generator=gen),
                     s2=torch.rand(N, S, generator=gen), h2=torch.rand(N, M, H, generator=gen))
        own = agent.actor(part.h).detach()  # (N, M, 2)
    else:
        agent = MAGRDPG(H, S, M, 6, (8,), 0.9, 0.1, 1e-3, 1e-3, burn_in=2, unroll=U, actor_robots=1,
                        actor_others="replay")
        part = Windows(x=torch.rand(N, M, 2 + U + 1, H, generator=gen), off=torch.tensor([0, 1, 2]),
                       s=torch.rand(N, U, S, generator=gen), a=torch.rand(N, U, M, 2, generator=gen),
                       r=torch.rand(N, U, generator=gen), s2=torch.rand(N, U, S, generator=gen))
        own = agent.policy_actions(part, None).detach()  # (N·U, M, 2)
    rows = agent.rows(part)
    sel = torch.tensor([[1], [3], [0]])
    agent.robot_subset = lambda n, m: sel
    seen = []
    critic = agent.critic
    agent.critic = lambda s, a: (seen.append(a.detach().clone()), critic(s, a))[1]
    agent.actor_step_parts([(part, False)], [rows], len(rows.s))
    a_q = seen[0]  # the actions the actor step evaluated Q at
    chosen = sel.repeat_interleave(a_q.shape[0] // N, dim=0)[:, 0]  # (N',) robot chosen in each row
    mask = torch.zeros(a_q.shape[:2], dtype=torch.bool)
    mask[torch.arange(a_q.shape[0]), chosen] = True
    torch.testing.assert_close(a_q[~mask], rows.a[~mask])
    torch.testing.assert_close(a_q[mask], own[mask], rtol=1e-5, atol=1e-6)


def test_output_layer_is_float32_inside_a_bf16_autocast():
    """OutputLinear is nn.Linear bit for bit outside autocast, and keeps float32 output inside a bf16 autocast."""
    from learn.networks import OutputLinear
    torch.manual_seed(3)
    out, ref = OutputLinear(7, 2), torch.nn.Linear(7, 2)
    ref.load_state_dict(out.state_dict())
    x = torch.randn(5, 7)
    assert torch.equal(out(x), ref(x))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert ref(x).dtype == torch.bfloat16 and out(x).dtype == torch.float32
        y = out(x.bfloat16())  # a bfloat16 input (a hidden layer's) is widened, then multiplied in float32
    assert torch.equal(y, ref(x.bfloat16().float()))


@pytest.mark.parametrize("kind", ["mlp", "gru"])
def test_bf16_update_runs_hidden_layers_in_bfloat16(kind):
    """precision='bf16': hidden layers of the update compute in bfloat16, Q, weights and Adam stay float32, and the
    gradients point where the float32 ones do (MLP transitions and GRU windows)."""
    from learn.magrdpg import MAGRDPG
    from learn.replay import Batch, Windows
    N, M, S, H, U = 16, 4, 2 + 3 * 4, 5, 3
    gen = torch.Generator().manual_seed(8)
    if kind == "mlp":
        part = Batch(s=torch.rand(N, S, generator=gen), h=torch.rand(N, M, H, generator=gen),
                     a=torch.rand(N, M, 2, generator=gen), r=torch.rand(N, generator=gen),
                     s2=torch.rand(N, S, generator=gen), h2=torch.rand(N, M, H, generator=gen))
    else:
        part = Windows(x=torch.rand(N, M, 2 + U + 1, H, generator=gen), off=torch.randint(0, 3, (N,), generator=gen),
                       s=torch.rand(N, U, S, generator=gen), a=torch.rand(N, U, M, 2, generator=gen),
                       r=torch.rand(N, U, generator=gen), s2=torch.rand(N, U, S, generator=gen))
    agents = {}
    for precision in ("fp32", "bf16"):
        torch.manual_seed(9)
        if kind == "mlp":
            agents[precision] = MAGDDPG(H, S, M, (16,), (32, 32), 0.9, 0.1, 1e-2, 1e-2, precision=precision)
        else:
            agents[precision] = MAGRDPG(H, S, M, 16, (32, 32), 0.9, 0.1, 1e-2, 1e-2, burn_in=2, unroll=U,
                                        precision=precision)
    hidden_dtypes = []
    agents["bf16"].critic.net[0].register_forward_hook(lambda m, i, o: hidden_dtypes.append(o.dtype))
    stats = {p: agents[p].update_parts([(part, False)]) for p in agents}
    assert hidden_dtypes and set(hidden_dtypes) == {torch.bfloat16}
    for p in ("actor", "critic", "actor_target", "critic_target"):
        assert all(t.dtype == torch.float32 for t in getattr(agents["bf16"], p).parameters())
    for net in ("critic", "actor"):  # the arithmetic differs, the gradient direction does not (to 1 %)
        g = {p: torch.cat([t.grad.flatten() for t in getattr(agents[p], net).parameters()]) for p in agents}
        assert not torch.equal(g["bf16"], g["fp32"])
        assert torch.nn.functional.cosine_similarity(g["bf16"], g["fp32"], dim=0) > 0.99, net
    assert abs(stats["bf16"].q_mean - stats["fp32"].q_mean) < 0.05 * abs(stats["fp32"].q_mean) + 1e-3


def test_precision_is_validated():
    """An unknown --precision is a one-line ConfigError naming the choices."""
    from learn.config import ConfigError, TrainConfig
    with pytest.raises(ConfigError, match="precision must be one of fp32, bf16, got 'fp16'"):
        TrainConfig(precision="fp16").validate()
