"""assign_identities: binding identical-looking optical bodies to vehicles by their own telemetry (issue 28)."""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from visionpos.analysis.autopilot import assign_identities, identity_residuals

ODDS_1000 = 2 * np.log(1000.0)


def test_margins_on_a_hand_made_cost_matrix():
    # body 0 fits vehicle 0 (10) far better than vehicle 1 (100); body 1 the other way round
    a = assign_identities(np.array([[10.0, 100.0], [100.0, 10.0]]), reject_cost=1000.0, ambiguity=ODDS_1000)
    assert a.vehicle.tolist() == [0, 1]
    # the best assignment that moves either body: the swap, 100 + 100 = 200 against 20
    assert np.allclose(a.margin, [180.0, 180.0])
    assert a.candidates.tolist() == [1, 1]


def test_two_close_candidates_are_unresolved_and_a_body_nothing_fits_stays_unbound():
    cost = np.array([[10.0, 12.0, 500.0],
                     [12.0, 10.0, 500.0],
                     [900.0, 900.0, 900.0]])  # body 2 moves like no vehicle: its reject cost (300) wins
    a = assign_identities(cost, reject_cost=300.0, ambiguity=ODDS_1000)
    assert a.vehicle.tolist() == [0, 1, -1]
    assert np.allclose(a.margin[:2], [4.0, 4.0])  # 12 + 12 - 20
    assert np.isinf(a.margin[2])
    assert a.candidates[:2].tolist() == [2, 2]  # "two candidates"


def test_more_vehicles_than_bodies_and_an_incomparable_pair():
    cost = np.array([[50.0, np.nan, 5.0]])  # vehicle 1 has sent no telemetry
    a = assign_identities(cost, reject_cost=200.0, ambiguity=ODDS_1000)
    assert a.vehicle.tolist() == [2]
    assert np.isclose(a.margin[0], 45.0)  # the next best: vehicle 0


def _fleet_telemetry(rng, n_vehicles, n, moving):
    """Roll/pitch (n, 2) and body rates (n, 3) per vehicle: distinct smooth motions, or a vehicle at rest."""
    t = np.arange(n) / 50.0
    att, rate = [], []
    for v in range(n_vehicles):
        if moving:
            f = 0.7 + 0.31 * v
            ph = 1.3 * v
            r = np.stack([0.6 * np.sin(2 * np.pi * f * t + ph), 0.5 * np.cos(2 * np.pi * 1.1 * f * t + ph),
                          0.3 * np.sin(2 * np.pi * 0.5 * f * t + 2 * ph)], axis=1)
            a = np.stack([0.1 * np.sin(2 * np.pi * f * t + ph), 0.08 * np.cos(2 * np.pi * f * t + ph)], axis=1)
        else:
            r, a = np.zeros((n, 3)), np.zeros((n, 2))
        att.append(a)
        rate.append(r)
    return np.array(att), np.array(rate)


def _cost(rng, att, rate, perm, sig_att, sig_rate):
    """Cost (B, V): body b is vehicle perm[b] seen optically (its own noise); the autopilots' telemetry noisy."""
    B, V = len(perm), len(att)
    noisy_att = att + rng.normal(0, sig_att, att.shape)
    noisy_rate = rate + rng.normal(0, sig_rate, rate.shape)
    cost = np.empty((B, V))
    for b in range(B):
        o_att = att[perm[b]] + rng.normal(0, sig_att, att[0].shape)
        o_rate = rate[perm[b]] + rng.normal(0, sig_rate, rate[0].shape)
        for v in range(V):
            r = identity_residuals(noisy_att[v], noisy_rate[v], o_att, o_rate, 2 * sig_att, 2 * sig_rate, 0.0)
            cost[b, v] = float(np.sum(r * r))
    return cost


def test_a_moving_fleet_is_told_apart_and_a_still_one_is_not():
    rng = np.random.default_rng(7)
    n, n_veh = 50, 6  # one second at 50 Hz
    perm = np.array([3, 0, 5, 1, 4, 2])
    reject = chi2.ppf(1 - 1e-6, 5 * n)
    att, rate = _fleet_telemetry(rng, n_veh, n, moving=True)
    a = assign_identities(_cost(rng, att, rate, perm, 0.005, 0.02), reject, ODDS_1000)
    assert a.vehicle.tolist() == perm.tolist()
    assert (a.margin > ODDS_1000).all() and (a.candidates == 1).all()
    # on the ground, still: every pairing fits as well as any other, so no body may be bound with confidence
    att, rate = _fleet_telemetry(rng, n_veh, n, moving=False)
    still = assign_identities(_cost(rng, att, rate, perm, 0.005, 0.02), reject, ODDS_1000)
    assert (still.margin < ODDS_1000).all()
    assert (still.candidates > 1).all()
