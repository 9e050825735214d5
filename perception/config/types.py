"""The annotated number types of the config fields, their physical upper bounds, and the strict
base model of every config model.

A number field takes an int or a float, never a bool or a string (:func:`_number`), and every
physical quantity has an upper bound (the ``MAX_*`` constants below).
"""

from __future__ import annotations

import math
from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field
from pydantic_core import PydanticCustomError

#: Upper bounds of the physical quantities: generous for any rendezvous or docking scenario, and
#: small enough that their squares and products stay finite (``initial.range_m: 1e300`` made the
#: reward NaN). A value above one is refused naming the field and the bound.
MAX_RANGE_M = 1e5  # relative distances and sensor ranges [m]
MAX_SIZE_M = 1e3  # positions on the vehicles, radii, gates and tolerances [m]
MAX_SIGMA_M = 100.0  # noise sigmas and biases [m]
MAX_ALTITUDE_M = 1e8
MAX_PERIOD_S = 86_400.0  # periods and windows [s]
MAX_FRAME_PERIOD_S = 60.0  # one sensor frame (a control step) and the latencies [s]
MAX_SPEED_M_S = 100.0
MAX_ACCEL_M_S2 = 100.0
MAX_RATE_DEG_S = 360.0
MAX_MASS_KG = 1e6
MAX_FORCE = 1e5  # thrust [N] and torque [N m]
MAX_ISP_S = 1e5
MAX_FACTOR = 1e6  # dimensionless factors and reward weights
MAX_COUNT = 1_000_000_000  # frame counters and candidate budgets


def _number(value: Any) -> Any:
    """Refuse what pydantic's lax mode would read as a number but is not one: ``True`` is not
    1 s, and ``"1.0"`` is a string (a YAML value in quotes), not a number."""
    if isinstance(value, (bool, np.bool_, str, bytes)):
        raise PydanticCustomError(
            "number_type", "a number, not {kind}", {"kind": f"a {type(value).__name__}"}
        )
    return value


#: Any finite number (an int is a float); the quantities below add their bounds.
Float = Annotated[float, BeforeValidator(_number), Field(allow_inf_nan=False)]
Int = Annotated[int, BeforeValidator(_number)]
PositiveFloat = Annotated[Float, Field(gt=0, le=MAX_FACTOR)]
NonNegFloat = Annotated[Float, Field(ge=0, le=MAX_FACTOR)]
UnitFloat = Annotated[Float, Field(ge=0, le=1)]
FiniteFloat = Annotated[Float, Field(ge=-MAX_FACTOR, le=MAX_FACTOR)]
Weight = FiniteFloat
Range = Annotated[Float, Field(gt=0, le=MAX_RANGE_M)]
NonNegRange = Annotated[Float, Field(ge=0, le=MAX_RANGE_M)]
Size = Annotated[Float, Field(gt=0, le=MAX_SIZE_M)]
Offset = Annotated[Float, Field(ge=-MAX_SIZE_M, le=MAX_SIZE_M)]
Vec3 = tuple[Offset, Offset, Offset]
Angle = Annotated[Float, Field(ge=-360, le=360)]
Angles3 = tuple[Angle, Angle, Angle]
FieldOfView = Annotated[Float, Field(gt=0, lt=180)]
SmallAngle = Annotated[Float, Field(ge=0, le=math.pi)]
Sigma = Annotated[Float, Field(ge=0, le=MAX_SIGMA_M)]
Period = Annotated[Float, Field(gt=0, le=MAX_PERIOD_S)]
NonNegPeriod = Annotated[Float, Field(ge=0, le=MAX_PERIOD_S)]
FramePeriod = Annotated[Float, Field(gt=0, le=MAX_FRAME_PERIOD_S)]
Latency = Annotated[Float, Field(ge=0, le=MAX_FRAME_PERIOD_S)]
Speed = Annotated[Float, Field(gt=0, le=MAX_SPEED_M_S)]
NonNegSpeed = Annotated[Float, Field(ge=0, le=MAX_SPEED_M_S)]
Rate = Annotated[Float, Field(ge=0, le=MAX_RATE_DEG_S)]
NonNegMass = Annotated[Float, Field(ge=0, le=MAX_MASS_KG)]
Force = Annotated[Float, Field(gt=0, le=MAX_FORCE)]


class StrictModel(BaseModel):
    """Base of every config model: unknown keys are errors, assignments are validated."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, frozen=False)
