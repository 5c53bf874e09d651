"""Reference solutions of the safety filter's QP, shared by the tests of the JAX and the numpy solver.

The QP (both filters): min_{u, s} ||u − u_nom||² + ρ s²  s.t.  â_j · u + s ≥ b̂_j (present rows, â_j = a_j/||a_j||,
b̂_j = b_j/||a_j||),  −u_max ≤ u ≤ u_max. It is strictly convex, so its solution is unique and any KKT
point is it. :func:`reference_qp` finds it by brute force (enumerate active sets, check KKT); :func:`osqp_qp`
asks a maintained solver (OSQP) as an independent check of the enumeration and of both solvers.
"""

from __future__ import annotations

import itertools

import numpy as np


def qp_rows(A, b, mask, u_max, rho):
    """(G, h): the QP as min ½||x − x0||² s.t. G x ≥ h in x = (u, √ρ s), over the present rows and the box."""
    A, b = np.asarray(A, float)[mask], np.asarray(b, float)[mask]
    nrm = np.linalg.norm(A, axis=1)
    keep = nrm > 1e-9  # a row with a ≈ 0 cannot be influenced by u: both filters ignore it
    A, b = A[keep] / nrm[keep, None], b[keep] / nrm[keep]
    u_max = np.broadcast_to(np.asarray(u_max, float), (3,))
    eye = np.eye(3)
    G = np.block([[A, np.full((len(b), 1), 1.0 / np.sqrt(rho))], [eye, np.zeros((3, 1))], [-eye, np.zeros((3, 1))]])
    return G, np.concatenate([b, -u_max, -u_max])


def reference_qp(u_nom, A, b, mask, u_max, rho=1e6):
    """Exact float64 (u, s) by enumerating active sets (≤ 4 independent rows in R^4) and checking KKT.

    For an active set S the candidate is x = x0 + G_Sᵀ ν with G_S x = h_S; it is the optimum iff ν ≥ 0
    and x is feasible. Sets of dependent rows (duplicates; the slack column makes good sets' Gram
    matrices reach condition ~1e7) are skipped. Tolerances 1e-7: |x| reaches 1e4 when very infeasible.
    """
    G, h = qp_rows(A, b, mask, u_max, rho)
    x0 = np.append(np.asarray(u_nom, float), 0.0)
    if np.all(G @ x0 >= h - 1e-12):
        return x0[:3], 0.0
    for k in range(1, 5):
        S = np.array(list(itertools.combinations(range(len(h)), k)))
        N = G[S]  # [sets, k, 4]
        gram = N @ N.transpose(0, 2, 1)
        ok = np.linalg.cond(gram) < 1e13
        N, S, gram = N[ok], S[ok], gram[ok]
        nu = np.linalg.solve(gram, (h[S] - N @ x0)[..., None])[..., 0]
        x = x0 + np.einsum("skd,sk->sd", N, nu)
        good = np.all(nu >= -1e-7, 1) & np.all(x @ G.T - h >= -1e-7, 1)
        if good.any():
            x = x[np.argmax(good)]
            return x[:3], x[3] / np.sqrt(rho)
    raise AssertionError("no KKT point found")


def osqp_qp(u_nom, A, b, mask, u_max, rho=1e6):
    """(u, s) from OSQP on the same QP in (u, s), with solution polishing (an exact solve on the active set
    OSQP found: its result is then as accurate as the KKT system's rounding, ~1e-9 here, not ADMM's eps).
    Returns None where OSQP did not solve and polish."""
    import osqp
    import scipy.sparse as sp

    G, h = qp_rows(A, b, mask, u_max, rho)
    C = G.copy()
    C[:, 3] *= np.sqrt(rho)  # back to the slack s itself: a_j · u + s ≥ b_j
    P = sp.csc_matrix(np.diag([2.0, 2.0, 2.0, 2.0 * rho]))
    q = np.append(-2.0 * np.asarray(u_nom, float), 0.0)
    prob = osqp.OSQP()
    prob.setup(P, q, sp.csc_matrix(C), h, np.full(len(h), np.inf), verbose=False, eps_abs=1e-10, eps_rel=1e-10,
               max_iter=200_000, polishing=True, polish_refine_iter=10)
    res = prob.solve(raise_error=False)  # an unsolved instance is reported as None, not raised
    if res.info.status != "solved" or res.info.status_polish != 1:
        return None
    return res.x[:3], res.x[3]
