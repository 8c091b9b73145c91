"""CiA 402 over CANopen, cyclic synchronous torque: frame codecs (`codec`), the 402 power
state machine (`statemachine`) and the host-side driver (`host`)."""
