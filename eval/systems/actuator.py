"""The robot's actuator as a Drake system between the safety filter and the joints.

Input "qdot_cmd" (6,) rad/s: the filter's command (its zero-order hold). Output "qdot"
(6,) rad/s: the velocity the joints move at over the coming control period
(safety.actuator.ActuatorModel.advance from the actuator's state and the command, a
direct feedthrough, so that with an ideal model it is the command itself and the loop
is the ideal one). Output "state" ((1 + delay) x 6,): the last applied velocity, then
the queued commands, oldest first (what the controller reports and the filter was told;
no feedthrough). One periodic update at the control rate stores the applied velocity and
shifts the queue, at the same instants as the integrator that reads "qdot".
Units: s, rad.
"""
from __future__ import annotations

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from safety.actuator import ActuatorModel


class ActuatorSystem(LeafSystem):
    """`model` (ActuatorModel) at control period `dt_s` for n joints."""

    def __init__(self, model: ActuatorModel, dt_s: float, n: int = 6):
        super().__init__()
        self.model, self.dt, self.n = model, float(dt_s), n
        self.delay = model.delay_steps(dt_s)
        self._cmd = self.DeclareVectorInputPort("qdot_cmd", n)
        self._state = self.DeclareDiscreteState((1 + self.delay) * n)
        self.DeclareVectorOutputPort("qdot", n, self._calc_qdot)
        self.DeclareStateOutputPort("state", self._state)
        self.DeclarePeriodicDiscreteUpdateEvent(self.dt, 0.0, self._update)

    def applied(self, context) -> np.ndarray:
        """The velocity (n,) rad/s applied from the context's time on."""
        x = context.get_discrete_state(self._state).get_value()
        n = self.n
        target = x[n:2 * n] if self.delay else self._cmd.Eval(context)
        return self.model.advance(x[:n], target, self.dt)

    def _calc_qdot(self, context, output: BasicVector) -> None:
        output.SetFromVector(self.applied(context))

    def _update(self, context, discrete_state) -> None:
        x = context.get_discrete_state(self._state).get_value()
        n = self.n
        new = np.empty_like(x)
        new[:n] = self.applied(context)
        if self.delay:
            new[n:-n] = x[2 * n:]
            new[-n:] = self._cmd.Eval(context)
        discrete_state.get_mutable_vector(self._state).SetFromVector(new)
