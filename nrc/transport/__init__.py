"""Light transport: phase function, free-flight sampling, transmittance estimators, lights."""
