"""Run AvaFrame's com1DFA on one of its cases as the peer of bench.avaframe_peers (needs ``pip install
avaframe==2.1``, in any Python; torchslide does not need it): Voellmy with com1DFA's default mu 0.155 and
xi 4000 m/s^2, no entrainment, the DEM remeshed to 10 m, the release polygons 1 m thick, tEnd 400 s. Writes
into the case folder (AVADIR/Outputs/com1DFA/peakFiles, AVADIR/Inputs/remeshedRasters).

    cp -r AvaFrame/avaframe/data/avaWog peers/avaWog
    python -m bench.com1dfa_run peers/avaWog
"""
from __future__ import annotations

import sys
import time


def main(ava: str) -> int:
    import avaframe.in3Utils.initializeProject as init_project
    from avaframe.com1DFA import com1DFA
    from avaframe.in3Utils import cfgUtils, logUtils

    cfg_main = cfgUtils.getGeneralConfig()
    cfg_main["MAIN"]["avalancheDir"] = ava
    cfg_main["FLAGS"]["savePlot"] = "False"
    cfg_main["FLAGS"]["createReport"] = "False"
    logUtils.initiateLogger(ava, "com1dfa_run")
    init_project.cleanSingleAvaDir(ava, deleteOutput=True)
    cfg = cfgUtils.getModuleConfig(com1DFA, ava, toPrint=False)
    general = cfg["GENERAL"]
    general.update({"simTypeList": "null", "frictModel": "Voellmy", "meshCellSize": "10", "relThFromFile": "False",
                    "relTh": "1.0", "tEnd": "400"})
    t0 = time.perf_counter()
    com1DFA.com1DFAMain(cfg_main, cfgInfo=cfg)
    print(f"com1DFA {ava}: {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1]))
