"""The benchmark's baseline: a straightforward float64 NumPy + ``scipy.spatial.cKDTree`` HEDGER.

Algorithms 1 and 2 as in ``hedger_jax`` (same conventions: scaled inputs, K = the
``max_neighbours`` nearest stored points within ``k_thresh``, IVH with an intercept column on
the query-centred neighbours, Gaussian-weighted local linear fit, region updates, reverse
replay), written the obvious way a NumPy user would: one Python call per query, a cKDTree of
the points present at the start of each episode (rebuilt per episode, like the grid index)
plus a NumPy brute-force scan of the points added since. Nothing here imports ``hedger_jax``
or jax; it is single-threaded (cKDTree queries with ``workers=1``).
"""
from __future__ import annotations

import math
import time

import numpy as np
from scipy.spatial import cKDTree


class NumpyHedger:
    def __init__(self, *, dim, capacity, bandwidth, max_neighbours, k_min, alpha=0.8,
                 gamma=0.8, ridge=1e-6, ivh_tol=1e-3, default_value=0.0, offset=None,
                 scale=None, discrete_actions=None, action_low=-1.0, action_high=1.0,
                 greedy_samples=11, greedy_iters=8, greedy_tol=1e-3, min_weight=0.01):
        self.dim, self.capacity = dim, capacity
        self.h = bandwidth
        self.r = bandwidth * math.sqrt(math.log(1.0 / min_weight))
        self.k, self.k_min = max_neighbours, k_min
        self.alpha, self.gamma, self.ridge, self.ivh_tol = alpha, gamma, ridge, ivh_tol
        self.default = default_value
        self.offset = np.zeros(dim) if offset is None else np.asarray(offset, np.float64)
        self.scale = np.ones(dim) if scale is None else np.asarray(scale, np.float64)
        self.actions = None if discrete_actions is None else np.asarray(discrete_actions,
                                                                        np.float64)
        self.low, self.high = action_low, action_high
        self.n_samples, self.iters, self.tol = greedy_samples, greedy_iters, greedy_tol
        self.points = np.zeros((capacity, dim))
        self.values = np.zeros(capacity)
        self.size = 0
        self.refresh()

    # ------------------------------------------------------------------ memory
    def add(self, z, v):
        if self.size < self.capacity:
            self.points[self.size] = z
            self.values[self.size] = v
            self.size += 1

    def refresh(self):
        """Rebuild the kd-tree over the current points (start of an episode)."""
        self.n_tree = self.size
        self.tree = cKDTree(self.points[:self.size]) if self.size else None

    def neighbours(self, zs):
        """zs (m, d) -> list of (idx, d2) per query: the k nearest within r, nearest first."""
        m = zs.shape[0]
        if self.tree is not None:
            kk = min(self.k, self.n_tree)
            dist, idx = self.tree.query(zs, k=kk, distance_upper_bound=self.r, workers=1)
            dist, idx = dist.reshape(m, kk), idx.reshape(m, kk)
        else:
            dist = np.full((m, 0), np.inf)
            idx = np.zeros((m, 0), np.int64)
        out = []
        new = self.points[self.n_tree:self.size]
        for i in range(m):
            ok = np.isfinite(dist[i])
            ii, dd = idx[i][ok], dist[i][ok] ** 2
            if len(new):
                d2 = np.sum((new - zs[i]) ** 2, axis=1)
                sel = np.nonzero(d2 <= self.r ** 2)[0]
                if len(sel):
                    ii = np.concatenate([ii, sel + self.n_tree])
                    dd = np.concatenate([dd, d2[sel]])
                    o = np.argsort(dd, kind="stable")[:self.k]
                    ii, dd = ii[o], dd[o]
            out.append((ii, dd))
        return out

    # ------------------------------------------------------------------ Algorithm 1
    def _fit(self, z, idx, d2):
        n = len(idx)
        if n < self.k_min:
            return self.default, False
        X = np.empty((n, self.dim + 1))
        X[:, 0] = 1.0
        X[:, 1:] = self.points[idx] - z
        p = self.dim + 1
        G = X.T @ X
        G += self.ridge * np.trace(G) / p * np.eye(p)
        Gi = np.linalg.inv(G)
        lev = np.einsum("ij,jk,ik->i", X, Gi, X)
        if Gi[0, 0] > (1.0 + self.ivh_tol) * lev.max():
            return self.default, False
        w = np.exp(-d2 / self.h ** 2)
        Xw = X * w[:, None]
        A = Xw.T @ X
        A += self.ridge * np.trace(A) / p * np.eye(p)
        beta = np.linalg.solve(A, Xw.T @ self.values[idx])
        return float(beta[0]), True

    def predict_scaled(self, zs):
        """zs (m, d) -> (values (m,), known (m,), neighbour lists)."""
        nbs = self.neighbours(zs)
        vals = np.empty(len(zs))
        known = np.empty(len(zs), bool)
        for i, (idx, d2) in enumerate(nbs):
            vals[i], known[i] = self._fit(zs[i], idx, d2)
        return vals, known, nbs

    def scale_inputs(self, s, a):
        return (np.concatenate([np.broadcast_to(s, (len(a), len(s))), a], 1)
                - self.offset) * self.scale

    # ------------------------------------------------------------------ greedy
    def greedy(self, s):
        """-> (action (A,), value, known)."""
        if self.actions is not None:
            v, k, _ = self.predict_scaled(self.scale_inputs(s, self.actions))
            i = int(np.argmax(v))
            return self.actions[i], v[i], bool(k.any())
        xs = list(np.linspace(self.low, self.high, self.n_samples))
        v, k, _ = self.predict_scaled(self.scale_inputs(s, np.asarray(xs)[:, None]))
        fs, any_known, prev = list(v), bool(k.any()), np.nan
        for _ in range(self.iters):
            order = np.argsort(xs)
            xa, fa = np.asarray(xs)[order], np.asarray(fs)[order]
            b = int(np.argmax(fa))
            b = min(max(b, 1), len(xa) - 2)
            x0, x1, x2 = xa[b - 1:b + 2]
            f0, f1, f2 = fa[b - 1:b + 2]
            d01, d12 = (f1 - f0) / (x1 - x0), (f2 - f1) / (x2 - x1)
            c2 = (d12 - d01) / (x2 - x0)
            if not c2 < 0:
                break
            xv = float(np.clip(-(d01 - c2 * (x0 + x1)) / (2 * c2), x0, x2))
            fv, kv, _ = self.predict_scaled(self.scale_inputs(s, np.array([[xv]])))
            xs.append(xv), fs.append(fv[0])
            any_known |= bool(kv[0])
            if abs(xv - prev) < self.tol or xv in xs[:-1]:
                break
            prev = xv
        i = int(np.argmax(fs))
        return np.array([xs[i]]), fs[i], any_known

    # ------------------------------------------------------------------ Algorithm 2
    def train_step(self, s, a, r, s2, terminated):
        z = self.scale_inputs(s, a[None])[0]
        v, _, nbs = self.predict_scaled(z[None])
        q = v[0]
        q_next = 0.0 if terminated else self.greedy(s2)[1]
        q_new = q + self.alpha * (r + self.gamma * q_next - q)
        idx, d2 = nbs[0]
        if len(idx):
            w = np.exp(-d2 / self.h ** 2)
            self.values[idx] += w * (q_new - self.values[idx])
        self.add(z, q_new)


# ---------------------------------------------------------------------- mountain car
def mc_step(x, v, a):
    v = np.clip(v + 0.001 * np.clip(a, -1, 1) - 0.0025 * math.cos(3 * x), -0.07, 0.07)
    x = min(max(x + v, -1.2), 0.5)
    if x <= -1.2 and v < 0:
        v = 0.0
    done = x >= 0.5
    return x, v, (1.0 - abs(v) / 0.07) if done else 0.0, done


def run_episodes(agent: NumpyHedger, n_episodes: int, rng, max_steps=200, epsilon=0.2,
                 continuous=False):
    """epsilon-greedy episodes with reverse replay; returns the number of training points."""
    points = 0
    for _ in range(n_episodes):
        agent.refresh()
        x, v = rng.uniform(-1.2, 0.5), rng.uniform(-0.07, 0.07)
        episode = []
        for _t in range(max_steps):
            s = np.array([x, v])
            if rng.uniform() < epsilon:
                a = (np.array([rng.uniform(-1, 1)]) if continuous
                     else agent.actions[rng.integers(len(agent.actions))])
            else:
                a = agent.greedy(s)[0]
            x, v, r, done = mc_step(x, v, float(a[0]))
            episode.append((s, a, r, np.array([x, v]), done))
            if done:
                break
        for tr in reversed(episode):
            agent.train_step(*tr)
        points += len(episode)
    return points


def time_episodes(agent, n_episodes, seed=0, continuous=False):
    rng = np.random.default_rng(seed)
    t = time.perf_counter()
    pts = run_episodes(agent, n_episodes, rng, continuous=continuous)
    return pts, time.perf_counter() - t
