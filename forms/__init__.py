"""Physics of mvfem as UFL: membrane kinematics, strain-energy laws, load and constraint terms.

Imports ufl only: no PETSc, no files, no MPI.
"""

from .kinematics import (Membrane, cauchy_stress, deformed_tangents, fibre_components,
                         fibre_stretch_squared, first_invariant, green_strain, membrane,
                         membrane_c33, second_piola, surface_metric, unit_normal)
from .materials import (LAWS, exponent, holzapfel, is_exponential, law_parameters, may_newman_yin,
                        neo_hookean, svk, uses_fibre)

__all__ = [
    "Membrane", "membrane", "surface_metric", "deformed_tangents", "membrane_c33",
    "first_invariant", "fibre_components", "fibre_stretch_squared", "green_strain",
    "second_piola", "cauchy_stress", "unit_normal",
    "LAWS", "law_parameters", "uses_fibre", "is_exponential", "exponent", "svk", "may_newman_yin", "holzapfel", "neo_hookean",
]
