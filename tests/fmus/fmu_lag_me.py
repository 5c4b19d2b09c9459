"""A first-order lag as an FMI 3.0 model-exchange FMU (built by pythonfmu3 in the tests):
tau·dx/dt = K·(u − u0) − x, y = y0 + x; the importer integrates it."""

from pythonfmu3 import (
    Float64,
    Fmi3Causality,
    Fmi3Initial,
    Fmi3SlaveBase,
    Fmi3Variability,
    ModelExchange,
)


class LagMe(Fmi3SlaveBase, ModelExchange):
    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.author = "autotune tests"
        self.description = "First-order lag, model exchange (FMI 3.0)"
        self.time = 0.0
        self.K = 2.0
        self.tau = 10.0
        self.u0 = 50.0
        self.y0 = 50.0
        self.u = 50.0
        self.x = 0.0
        self.der_x = 0.0
        self.register_variable(
            Float64(
                "time", causality=Fmi3Causality.independent, variability=Fmi3Variability.continuous
            )
        )
        for name in ("K", "tau", "u0", "y0"):
            self.register_variable(
                Float64(name, causality=Fmi3Causality.parameter, variability=Fmi3Variability.fixed)
            )
        self.register_variable(
            Float64("u", causality=Fmi3Causality.input, variability=Fmi3Variability.continuous)
        )
        self.register_variable(
            Float64(
                "x",
                causality=Fmi3Causality.local,
                variability=Fmi3Variability.continuous,
                initial=Fmi3Initial.exact,
            )
        )
        self.register_variable(
            Float64(
                "der_x",
                causality=Fmi3Causality.local,
                variability=Fmi3Variability.continuous,
                derivative=self.vars_index("x"),
            )
        )
        self.register_variable(  # computed from the state whenever it is read
            Float64(
                "y",
                causality=Fmi3Causality.output,
                variability=Fmi3Variability.continuous,
                getter=lambda: self.y0 + self.x,
            )
        )

    def vars_index(self, name):
        return next(vr for vr, v in self.vars.items() if v.name == name)

    def exit_initialization_mode(self):
        self.x = self.K * (self.u - self.u0)  # at rest with the input it starts with

    def get_continuous_state_derivatives(self):
        self.der_x = (self.K * (self.u - self.u0) - self.x) / self.tau
        return [self.der_x]
