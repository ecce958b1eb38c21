"""The EM test of each landmark: M-step weights (eq. 14), outlier gate, E-step row scales
(eq. 16), variance factors, and the weight models; see docs/design/em_sam_core.md."""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from em_sam_node.core.assembly import BuiltProblem, MappingData
from em_sam_node.core.em_types import SEED_KERNELS, EmConfig
from em_sam_node.core.factors import observation_innovations
from em_sam_node.core.problem import Estimate, SlamProblem
from em_sam_node.core.robust_kernels import RobustKernel
from slam_core.arrays import FloatArray, IntArray
from slam_core.lazy_stats import chi2

ROW_SCALE_FLOOR = 1e-3


@functools.lru_cache(maxsize=65536)
def chi2_quantile(probability: float, dof: int) -> float:
    """The chi-square quantile, cached (the online smoother tests landmarks one at a time)."""
    return float(chi2.ppf(probability, dof))


def squared_mahalanobis(innovations: FloatArray, covariances: FloatArray) -> FloatArray:
    """Return eta_k^T C_k^-1 eta_k (K,) for innovations (K,2) and covariances (K,2,2)."""
    solved = np.linalg.solve(covariances, innovations[..., None])[..., 0]
    result: FloatArray = np.einsum('ki,ki->k', innovations, solved)
    return result


def observation_noise_scales(innovations: FloatArray, obs_cov: FloatArray) -> FloatArray:
    """Return the a-posteriori variance factors (2,) of range and bearing, each at least 1."""
    if len(innovations) == 0:
        return np.ones(2)
    variances = np.stack([obs_cov[:, 0, 0], obs_cov[:, 1, 1]], axis=1)
    factors = np.median(innovations**2 / variances, axis=0) / float(chi2.median(1))
    result: FloatArray = np.maximum(factors, 1.0)
    return result


def with_noise_scales(data: MappingData, factors: FloatArray) -> MappingData:
    """Return ``data`` with every sighting covariance scaled by D C D, D = diag(sqrt(factors))."""
    root = np.sqrt(np.asarray(factors, dtype=np.float64))
    return dataclasses.replace(
        data, obs_cov=data.obs_cov * root[None, :, None] * root[None, None, :]
    )


def gate_outliers(
    config: EmConfig, mahalanobis: FloatArray, obs_landmark: IntArray, num_landmarks: int
) -> np.ndarray:
    """Return a (K,) mask of isolated gross outlier sightings (robust mode)."""
    gate = chi2_quantile(1.0 - config.gate_probability, 2)
    gated = np.zeros(mahalanobis.shape, dtype=bool)
    counts = np.bincount(obs_landmark, minlength=num_landmarks)
    allowed = np.floor(config.max_gated_fraction * counts).astype(np.int64)
    suspects = np.flatnonzero(mahalanobis > gate)
    if len(suspects) == 0:
        return gated
    order = suspects[np.lexsort((-mahalanobis[suspects], obs_landmark[suspects]))]
    landmark_of = obs_landmark[order]
    starts = np.r_[0, np.flatnonzero(np.diff(landmark_of)) + 1]
    rank = np.arange(len(order)) - np.repeat(starts, np.diff(np.r_[starts, len(order)]))
    gated[order[rank < allowed[landmark_of]]] = True
    return gated


class WeightModel(Protocol):
    """How EM-SAM weighs landmarks ('paper' or 'robust', chosen by ``weight_model``)."""

    @property
    def config(self) -> EmConfig: ...

    @property
    def gates(self) -> bool:
        """Whether the model gates isolated outlier sightings."""
        ...

    @property
    def seeds_from_all_static(self) -> bool:
        """The first E-step: the all-static solve (True) or the incremental robust seed."""
        ...

    def test_covariances(self, obs_cov: FloatArray, obs_z: FloatArray) -> FloatArray | None:
        """Sighting covariances (K, 2, 2) for the test, or None to use the model's."""
        ...

    def model_variance_m2(self) -> float:
        """The isotropic model error added to a position test, m^2."""
        ...

    def noise_scales(
        self, data: MappingData, built: BuiltProblem, problem: SlamProblem, estimate: Estimate
    ) -> FloatArray:
        """The capped variance factors (2,) of range and bearing at ``estimate``."""
        ...

    def gate(
        self, mahalanobis: FloatArray, obs_landmark: IntArray, num_landmarks: int
    ) -> np.ndarray:
        """A (K,) mask of the sightings left out of the M-step."""
        ...

    def m_step(
        self,
        mahalanobis: FloatArray,
        obs_landmark: IntArray,
        num_landmarks: int,
        included: np.ndarray,
    ) -> FloatArray:
        """New landmark weights (L,) in [0, 1] from the ``included`` sightings' (K,) distances."""
        ...

    def row_scales(
        self, weights: FloatArray, obs_landmark: IntArray, gated: np.ndarray
    ) -> FloatArray:
        """The E-step row scale of every sighting (K,); gated rows at ROW_SCALE_FLOOR."""
        ...

    def final_kernel(self) -> RobustKernel | None:
        """The final solve's kernel on the static sightings, or None."""
        ...


def _counts_and_sums(
    mahalanobis: FloatArray, obs_landmark: IntArray, num_landmarks: int, included: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    counts = np.bincount(obs_landmark[included], minlength=num_landmarks)
    sums = np.bincount(
        obs_landmark[included], weights=mahalanobis[included], minlength=num_landmarks
    )
    return counts, sums


def _rows(scale: FloatArray, obs_landmark: IntArray, gated: np.ndarray) -> FloatArray:
    rows = np.maximum(scale[obs_landmark], ROW_SCALE_FLOOR)
    rows[gated] = ROW_SCALE_FLOOR
    return rows


@dataclass(frozen=True)
class PaperWeights:
    """The paper's model: eq. 14, rows scaled by w, no gate, the all-static first E-step."""

    config: EmConfig
    gates: bool = False
    seeds_from_all_static: bool = True

    def test_covariances(self, obs_cov: FloatArray, obs_z: FloatArray) -> FloatArray | None:
        return None

    def model_variance_m2(self) -> float:
        return 0.0

    def noise_scales(
        self, data: MappingData, built: BuiltProblem, problem: SlamProblem, estimate: Estimate
    ) -> FloatArray:
        return np.ones(2)

    def gate(
        self, mahalanobis: FloatArray, obs_landmark: IntArray, num_landmarks: int
    ) -> np.ndarray:
        return np.zeros(mahalanobis.shape, dtype=bool)

    def m_step(
        self,
        mahalanobis: FloatArray,
        obs_landmark: IntArray,
        num_landmarks: int,
        included: np.ndarray,
    ) -> FloatArray:
        _, sums = _counts_and_sums(mahalanobis, obs_landmark, num_landmarks, included)
        return np.clip(1.0 - sums / (2.0 * self.config.lagrange_lambda), 0.0, 1.0)

    def row_scales(
        self, weights: FloatArray, obs_landmark: IntArray, gated: np.ndarray
    ) -> FloatArray:
        return _rows(weights, obs_landmark, gated)

    def final_kernel(self) -> RobustKernel | None:
        return None


@dataclass(frozen=True)
class RobustWeights:
    """The robust model: a chi-square test per landmark, rows scaled by sqrt(w), the gate."""

    config: EmConfig
    gates: bool = True
    seeds_from_all_static: bool = False

    def test_covariances(self, obs_cov: FloatArray, obs_z: FloatArray) -> FloatArray | None:
        model_error = self.config.model_error_m
        if model_error == 0 or len(obs_cov) == 0:
            return None
        extra = np.zeros_like(obs_cov)
        extra[:, 0, 0] = model_error**2
        extra[:, 1, 1] = (model_error / np.maximum(obs_z[:, 0], 1e-3)) ** 2
        result: FloatArray = obs_cov + extra
        return result

    def model_variance_m2(self) -> float:
        return float(self.config.model_error_m**2)

    def noise_scales(
        self, data: MappingData, built: BuiltProblem, problem: SlamProblem, estimate: Estimate
    ) -> FloatArray:
        if not self.config.estimate_noise_scale:
            return np.ones(2)
        factors = observation_noise_scales(
            observation_innovations(problem, estimate), data.obs_cov[built.observation_rows]
        )
        result: FloatArray = np.minimum(factors, self.config.max_noise_scale)
        return result

    def gate(
        self, mahalanobis: FloatArray, obs_landmark: IntArray, num_landmarks: int
    ) -> np.ndarray:
        return gate_outliers(self.config, mahalanobis, obs_landmark, num_landmarks)

    def m_step(
        self,
        mahalanobis: FloatArray,
        obs_landmark: IntArray,
        num_landmarks: int,
        included: np.ndarray,
    ) -> FloatArray:
        counts, sums = _counts_and_sums(mahalanobis, obs_landmark, num_landmarks, included)
        dof = np.maximum(2 * counts - 2, 1)
        level = 1.0 - self.config.false_alarm_probability
        quantile = np.array([chi2_quantile(level, int(n)) for n in dof.tolist()])
        excess = np.maximum(sums - dof, 0.0)
        weights: FloatArray = np.clip(1.0 - excess / (2.0 * (quantile - dof)), 0.0, 1.0)
        weights[counts <= 1] = 1.0  # a single sighting carries no evidence of motion
        return weights

    def row_scales(
        self, weights: FloatArray, obs_landmark: IntArray, gated: np.ndarray
    ) -> FloatArray:
        return _rows(np.sqrt(weights), obs_landmark, gated)

    def final_kernel(self) -> RobustKernel | None:
        if self.config.final_kernel == 'none':
            return None
        return SEED_KERNELS[self.config.final_kernel](self.config.final_kernel_scale)


WEIGHT_MODELS: dict[str, type[PaperWeights] | type[RobustWeights]] = {
    'paper': PaperWeights,
    'robust': RobustWeights,
}


def weight_model(config: EmConfig) -> WeightModel:
    """The weight model ``config.mode`` names."""
    return WEIGHT_MODELS[config.mode](config)
