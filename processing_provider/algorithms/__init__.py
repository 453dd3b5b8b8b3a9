"""One module per algorithm; ALGORITHMS lists the classes the provider registers, in menu order."""
from .applycalibration import ApplyCalibration
from .assessaccuracy import AssessAccuracy
from .blockadjust import BlockAdjust
from .calibratelookangle import CalibrateLookAngle
from .collectgcps import CollectGcps
from .orthorectify import Orthorectify
from .refinerpc import RefineRpc
from .rpcinfo import RpcInfo
from .simulatescene import SimulateScene

ALGORITHMS = [RpcInfo, SimulateScene, CollectGcps, RefineRpc, Orthorectify, CalibrateLookAngle, ApplyCalibration,
              AssessAccuracy, BlockAdjust]
