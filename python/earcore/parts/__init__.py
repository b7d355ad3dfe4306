"""Parts on the table: the RoboCup@Work part set as meshes (`catalogue`), the IROS 2018
pickup-point detector (`detector`, `objective`, `train`, `evaluate`) and picking from
its activations (`pickup`). Training needs torch (pip install 'earcore[learning]')."""
