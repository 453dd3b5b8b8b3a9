"""One module per algorithm; ALGORITHMS lists the classes the provider registers, in menu order."""
from .applycalibration import ApplyCalibration
from .applycalibrationbatch import ApplyCalibrationBatch
from .assessaccuracy import AssessAccuracy
from .blockadjust import BlockAdjust
from .bundleadjust import BundleAdjust
from .calibratelookangle import CalibrateLookAngle
from .collectgcps import CollectGcps
from .collectgcpsbatch import CollectGcpsBatch
from .orthorectify import Orthorectify
from .refinerpc import RefineRpc
from .refinerpcbatch import RefineRpcBatch
from .registerpanms import RegisterPanMs
from .rpcinfo import RpcInfo
from .simulatescene import SimulateScene

ALGORITHMS = [RpcInfo, SimulateScene, CollectGcps, RefineRpc, Orthorectify, CalibrateLookAngle, ApplyCalibration,
              AssessAccuracy, RegisterPanMs, BlockAdjust, BundleAdjust]
# Batch forms (issue 14): many scenes, resumable, threads or a Dask scheduler.
ALGORITHMS += [CollectGcpsBatch, RefineRpcBatch, ApplyCalibrationBatch]
