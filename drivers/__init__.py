"""CAN protocols of real drives (CiA 402, ODrive CANSimple): host-side and device-side codecs."""
