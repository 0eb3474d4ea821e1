"""PILCO's analytic parts in torch: GP dynamics, moment matching, RBF policy, saturating cost.

References (equation numbers cited in the functions):
- [DR11] M. P. Deisenroth, C. E. Rasmussen, "PILCO: A Model-Based and Data-Efficient Approach
  to Policy Search", ICML 2011.
- [D10] M. P. Deisenroth, "Efficient Reinforcement Learning using Gaussian Processes", PhD
  thesis, KIT 2010 (Sec. 2.3 moment matching; App. A.1 trigonometric moments).
- [RW06] C. E. Rasmussen, C. K. I. Williams, "Gaussian Processes for Machine Learning", 2006.

Everything is float64. Shapes: E input size, n training points, A outputs, D state size,
F action size. Gradients of every moment flow through torch autograd, which is exact (the
"analytic gradients" of [DR11] Sec. 2.3 without hand-written derivatives).
"""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

DTYPE = torch.float64
#: elements of one step's largest moment-matching tensor (A, A, n, n) above which the rollout
#: recomputes each step in the backward pass instead of keeping it (float64: 32 MB a step)
CHECKPOINT_ELEMENTS = 4_000_000


def _sym(matrix: Tensor) -> Tensor:
    return 0.5 * (matrix + matrix.mT)


def rbf_moments(
    m: Tensor,
    s: Tensor,
    x: Tensor,
    beta: Tensor,
    lengthscales: Tensor,
    signal_var: Tensor,
    inv_k: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Moments of f_a(z) = sum_i beta_ai k_a(z, x_i) for z ~ N(m, s), by moment matching.

    k_a(z, x) = signal_var_a exp(-|z - x|^2_{Lambda_a^-1} / 2), Lambda_a = diag(lengthscales_a^2).
    Shapes: m (E,), s (E,E), x (n,E), beta (A,n), lengthscales (A,E), signal_var (A,).
    Returns the mean (A,) ([DR11] eqs. 14-16), the covariance (A,A) ([DR11] eqs. 17-21,
    [D10] eqs. 2.53-2.55) and the input-output covariance Cov[z, f] (E,A) ([DR11] eq. 22).
    With ``inv_k`` (A,n,n) = (K_a + noise_a I)^-1 the f_a are GP posteriors and their
    expected latent variance signal_var_a - tr(inv_k_a Q_aa) is added on the diagonal
    ([DR11] eq. 21); without it the f_a are deterministic functions (the RBF policy).
    """
    n_out, n_in = beta.shape[0], m.shape[0]
    nu = x - m  # (n,E) training inputs relative to the input mean
    lam = lengthscales**2  # (A,E)
    inv_lam = 1.0 / lam

    # mean: q_ai = sf2_a |s Lambda_a^-1 + I|^-1/2 exp(-nu_i^T (s + Lambda_a)^-1 nu_i / 2)
    chol = torch.linalg.cholesky(s + torch.diag_embed(lam))  # (A,E,E)
    sol = torch.cholesky_solve(nu.T.expand(n_out, n_in, -1), chol)  # (A,E,n)
    maha = (nu.T * sol).sum(-2)  # (A,n)
    log_diag = torch.log(torch.diagonal(chol, dim1=-2, dim2=-1))
    logdet = 2.0 * log_diag.sum(-1) - torch.log(lam).sum(-1)
    q = signal_var[:, None] * torch.exp(-0.5 * maha - 0.5 * logdet[:, None])
    bq = beta * q
    mean = bq.sum(-1)
    cross = s @ (sol * bq[:, None, :]).sum(-1).T  # (E,A): s (s + Lambda_a)^-1 sum_i bq_ai nu_i

    # covariance: E[f_a f_b] = beta_a^T Q_ab beta_b, [DR11] eqs. 17-21
    nu_l = nu[None] * inv_lam[:, None, :]  # (A,n,E) Lambda_a^-1 nu_i
    log_k = torch.log(signal_var)[:, None] - 0.5 * (nu * nu_l).sum(-1)  # (A,n) log k_a(x_i, m)
    second, trace = _second_moments(s, nu_l, log_k, inv_lam, beta, inv_k)
    cov = second - torch.outer(mean, mean)
    if trace is not None:
        cov = cov + torch.diag(signal_var - trace)
    return mean, _sym(cov), cross


def _second_moments(
    s: Tensor, nu_l: Tensor, log_k: Tensor, inv_lam: Tensor, beta: Tensor, inv_k: Tensor | None
) -> tuple[Tensor, Tensor | None]:
    """E[f_a f_b] (A,A) and, with ``inv_k``, tr(inv_k_a Q_aa) (A,) ([DR11] eqs. 18-21).

    Q_abij = k_a(x_i,m) k_b(x_j,m) |R|^-1/2 exp(z_ij^T R^-1 s z_ij / 2) with
    R = s (Lambda_a^-1 + Lambda_b^-1) + I and z_ij = Lambda_a^-1 nu_i + Lambda_b^-1 nu_j.
    The quadratic form splits into a_i^T M a_i + b_j^T M b_j + 2 a_i^T M b_j (M = R^-1 s), so
    no (n,n,E) tensor is formed; Q_ba = Q_ab^T, so only pairs a <= b are computed.
    """
    n_out, n_in = beta.shape[0], s.shape[0]
    ia, ib = torch.triu_indices(n_out, n_out)
    r = s * (inv_lam[ia] + inv_lam[ib])[:, None, :] + torch.eye(n_in, dtype=s.dtype)  # (P,E,E)
    mat = _sym(torch.linalg.solve(r, s.expand(len(ia), n_in, n_in)))  # R^-1 s
    ta, tb = nu_l[ia] @ mat, nu_l[ib] @ mat  # (P,n,E)
    half_logdet = 0.5 * torch.linalg.slogdet(r)[1]
    row = log_k[ia] + 0.5 * (ta * nu_l[ia]).sum(-1) - half_logdet[:, None]  # (P,n)
    col = log_k[ib] + 0.5 * (tb * nu_l[ib]).sum(-1)
    big_q = torch.exp(torch.baddbmm(col[:, None, :], ta, nu_l[ib].mT) + row[:, :, None])
    pair = (beta[ia][:, None, :] @ big_q @ beta[ib][:, :, None])[:, 0, 0]  # (P,)
    upper = torch.zeros(n_out, n_out, dtype=s.dtype).index_put((ia, ib), pair)
    second = upper + upper.T - torch.diag(torch.diagonal(upper))
    if inv_k is None:
        return second, None
    diagonal = big_q[ia == ib]  # (A,n,n), pairs (a,a) in order
    return second, (inv_k * diagonal).sum((-2, -1))


def sin_moments(m: Tensor, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Moments of u = sin(y) for y ~ N(m, s) ([D10] App. A.1; [DR11] Sec. 2.2 squashing).

    Returns E[u] (F,), Cov[u] (F,F) and dC (F,F) = diag(E[cos y]) with Cov[y, u] = s dC
    (Stein's lemma), so the covariance of anything jointly Gaussian with y and u is Cov[., y] dC.
    """
    v = torch.diagonal(s)
    mean = torch.exp(-0.5 * v) * torch.sin(m)
    vsum = v[:, None] + v[None, :]
    e_sin_sin = 0.5 * (
        torch.exp(-0.5 * (vsum - 2.0 * s)) * torch.cos(m[:, None] - m[None, :])
        - torch.exp(-0.5 * (vsum + 2.0 * s)) * torch.cos(m[:, None] + m[None, :])
    )
    cov = _sym(e_sin_sin - torch.outer(mean, mean))
    return mean, cov, torch.diag(torch.exp(-0.5 * v) * torch.cos(m))


def expected_saturating_cost(m: Tensor, s: Tensor, target: Tensor, weight: Tensor) -> Tensor:
    """E[1 - exp(-(x - target)^T W (x - target) / 2)] for x ~ N(m, s) ([DR11] eqs. 24-25)."""
    eye = torch.eye(m.shape[0], dtype=m.dtype)
    sw_i = s @ weight + eye
    diff = m - target
    quad = diff @ weight @ torch.linalg.solve(sw_i, diff)
    return 1.0 - torch.exp(-0.5 * quad) / torch.sqrt(torch.linalg.det(sw_i))


class GaussianProcess:
    """Independent exact GPs, one per output, ARD squared-exponential kernels ([DR11] Sec. 2.1).

    Inputs ``x`` (n,E), targets ``y`` (n,A). Hyperparameters maximise the log marginal
    likelihood ([RW06] eq. 5.8) by L-BFGS, with a soft curb on lengthscales and the signal-to-
    noise ratio (as PILCO does) so that few, nearly noise-free points cannot make them explode.
    """

    def __init__(self, x: Tensor, y: Tensor) -> None:
        self.x = x.to(DTYPE)
        self.y = y.to(DTYPE)
        n_out = self.y.shape[1]
        several = len(self.x) > 1
        x_std = self.x.std(0).clamp_min(1e-3) if several else torch.ones(x.shape[1], dtype=DTYPE)
        y_std = self.y.std(0).clamp_min(1e-6) if several else 1e-3 * torch.ones(n_out, dtype=DTYPE)
        self._x_std = x_std
        self.log_ls = torch.log(x_std).repeat(n_out, 1)
        self.log_sf = torch.log(y_std)
        self.log_sn = torch.log(0.1 * y_std)
        self._refresh()

    # ------------------------------------------------------------------ hyperparameters
    @property
    def lengthscales(self) -> Tensor:
        return torch.exp(self.log_ls)

    @property
    def signal_var(self) -> Tensor:
        return torch.exp(2.0 * self.log_sf)

    @property
    def noise_var(self) -> Tensor:
        return torch.exp(2.0 * self.log_sn)

    def kernel(self, a: Tensor, b: Tensor, log_ls: Tensor, log_sf: Tensor) -> Tensor:
        """(A, len(a), len(b)) ARD squared-exponential kernel matrices."""
        ls = torch.exp(log_ls)[:, None, :]
        a_s, b_s = a / ls, b / ls  # (A,na,E), (A,nb,E)
        cross = a_s @ b_s.mT
        dist2 = (a_s**2).sum(-1)[..., :, None] + (b_s**2).sum(-1)[..., None, :] - 2.0 * cross
        return torch.exp(2.0 * log_sf)[:, None, None] * torch.exp(-0.5 * dist2.clamp_min(0.0))

    def _neg_log_likelihood(self, log_ls: Tensor, log_sf: Tensor, log_sn: Tensor) -> Tensor:
        n = self.x.shape[0]
        k = self.kernel(self.x, self.x, log_ls, log_sf)
        k = k + (torch.exp(2.0 * log_sn)[:, None, None] + 1e-10) * torch.eye(n, dtype=DTYPE)
        chol = torch.linalg.cholesky(k)
        alpha = torch.cholesky_solve(self.y.T[..., None], chol)[..., 0]  # (A,n)
        data_fit = 0.5 * (self.y.T * alpha).sum(-1)
        complexity = torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
        nll = (data_fit + complexity).sum() / n
        curb = ((log_ls - torch.log(self._x_std)) / math.log(100.0)) ** 30
        curb = curb.sum() + (((log_sf - log_sn) / math.log(500.0)) ** 30).sum()
        return nll + curb

    def fit(self, iterations: int = 100) -> None:
        """Optimise the hyperparameters (L-BFGS, strong Wolfe line search), then precompute."""
        params = [p.clone().requires_grad_(True) for p in (self.log_ls, self.log_sf, self.log_sn)]
        optimizer = torch.optim.LBFGS(
            params, lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe"
        )

        def closure() -> Tensor:
            optimizer.zero_grad()
            loss = self._neg_log_likelihood(*params)
            loss.backward()
            return loss

        try:
            optimizer.step(closure)
        except torch.linalg.LinAlgError:
            return  # keep the previous (initial) hyperparameters
        if all(torch.isfinite(p).all() for p in params):
            self.log_ls, self.log_sf, self.log_sn = (p.detach() for p in params)
            self._refresh()

    def _refresh(self) -> None:
        n = self.x.shape[0]
        k = self.kernel(self.x, self.x, self.log_ls, self.log_sf)
        k = k + (self.noise_var[:, None, None] + 1e-10) * torch.eye(n, dtype=DTYPE)
        self.inv_k = torch.cholesky_inverse(torch.linalg.cholesky(k))  # (A,n,n)
        self.beta = (self.inv_k @ self.y.T[..., None])[..., 0]  # (A,n)

    # ------------------------------------------------------------------ predictions
    def predict(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """Posterior mean and latent variance at deterministic inputs z (m,E): (m,A) each."""
        k_star = self.kernel(z.to(DTYPE), self.x, self.log_ls, self.log_sf)  # (A,m,n)
        mean = (k_star @ self.beta[..., None])[..., 0].T
        var = self.signal_var[:, None] - ((k_star @ self.inv_k) * k_star).sum(-1)
        return mean, var.T

    def moments(self, m: Tensor, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Predictive mean, covariance (latent + noise) and Cov[z, y] at z ~ N(m, s)."""
        mean, cov, cross = rbf_moments(
            m, s, self.x, self.beta, self.lengthscales, self.signal_var, self.inv_k
        )
        return mean, cov + torch.diag(self.noise_var), cross


class RBFPolicy(torch.nn.Module):
    """pi(e) = sin(sum_i w_i exp(-|e / scale - c_i|^2_{Lambda^-1} / 2)), actions in [-1, 1].

    The RBF network is [DR11] eq. 26 (a deterministic GP mean); the sine squashing keeps
    actions bounded with analytic moments ([DR11] Sec. 2.2, [D10] Sec. 3.5.1). The input ``e``
    is the reduced state minus the reduced goal, so the policy acts on the goal it is given;
    it is divided by a fixed per-dimension ``scale`` so centres and lengthscales are O(1) and
    one learning rate suits every parameter.
    """

    def __init__(
        self, centres: Tensor, action_dim: int, scale: Tensor, generator: torch.Generator
    ) -> None:
        super().__init__()
        n_basis, n_in = centres.shape
        self.register_buffer("scale", scale.to(DTYPE).clone())
        self.centres = torch.nn.Parameter(centres.to(DTYPE) / self.scale)
        weights = 0.1 * torch.randn(action_dim, n_basis, generator=generator, dtype=DTYPE)
        self.weights = torch.nn.Parameter(weights)
        self.log_ls = torch.nn.Parameter(torch.zeros(action_dim, n_in, dtype=DTYPE))

    def forward(self, e: Tensor) -> Tensor:
        """Actions (..., F) for error states e (..., D)."""
        ls = torch.exp(self.log_ls)  # (F,D)
        diff = (e[..., None, None, :] / self.scale - self.centres) / ls[:, None, :]
        basis = torch.exp(-0.5 * (diff**2).sum(-1))  # (...,F,nb)
        return torch.sin((basis * self.weights).sum(-1))

    def moments(self, m: Tensor, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """E[u], Cov[u] and Cov[e, u] (D,F) for e ~ N(m, s)."""
        ones = torch.ones(self.weights.shape[0], dtype=DTYPE)
        scaled_s = s / torch.outer(self.scale, self.scale)
        pre_m, pre_s, pre_c = rbf_moments(
            m / self.scale, scaled_s, self.centres, self.weights, torch.exp(self.log_ls), ones
        )
        mean, cov, d_cos = sin_moments(pre_m, pre_s)
        return mean, cov, self.scale[:, None] * (pre_c @ d_cos)


def propagate(
    m: Tensor, s: Tensor, gp: GaussianProcess, policy: RBFPolicy, goal: Tensor
) -> tuple[Tensor, Tensor]:
    """One step of p(x_t) -> p(x_t+1) ([DR11] Sec. 2.2, eqs. 10-12).

    u = pi(x - goal) is moment-matched into a joint Gaussian over (x, u); the GP predicts the
    change Delta with Cov[x, Delta]; x_t+1 = x_t + Delta.
    """
    n_x = m.shape[0]
    mu, su, cxu = policy.moments(m - goal, s)
    m_joint = torch.cat([m, mu])
    s_joint = torch.cat([torch.cat([s, cxu], 1), torch.cat([cxu.T, su], 1)], 0)
    md, sd, c_joint = gp.moments(m_joint, s_joint)
    c_xd = c_joint[:n_x]
    return m + md, _sym(s + sd + c_xd + c_xd.T)


def expected_return_cost(
    m0: Tensor,
    s0: Tensor,
    gp: GaussianProcess,
    policy: RBFPolicy,
    goal: Tensor,
    weight: Tensor,
    horizon: int,
) -> Tensor:
    """J(theta) = sum_{t=1..H} E[c(x_t)] ([DR11] eq. 2).

    Large GPs are checkpointed per step to save memory; smaller ones (the default sizes,
    A = 9 outputs and n = 100 points: 0.8 M elements a step) keep every step, which is
    faster; both give bitwise the same gradients, since the recomputation repeats the same
    operations."""
    n_out, n_points = gp.beta.shape
    step = propagate
    if n_out**2 * n_points**2 > CHECKPOINT_ELEMENTS:
        step = functools.partial(checkpoint, propagate, use_reentrant=False)
    m, s = m0, s0
    total = torch.zeros((), dtype=DTYPE)
    for _ in range(horizon):
        m, s = step(m, s, gp, policy, goal)
        total = total + expected_saturating_cost(m, s, goal, weight)
    return total
