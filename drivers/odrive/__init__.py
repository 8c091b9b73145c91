"""ODrive CANSimple (firmware 0.6): frame codecs (`codec`) and the host-side driver (`host`)."""
