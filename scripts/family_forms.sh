# Sourced by scripts/kinds_table.sh and scripts/offers_table.sh: the hidden forms of the
# second truth generator that the family matrix runs (examples/family_matrix: every form
# of persist::trapgen::hidden::ALL not held aside), and how each is simulated.

# The simulator's effects (`persist simulate lab --effect`) the offers table runs with
# SOURCE=lab (scripts/offers_table.sh, scripts/validation.sh offers_sim).
LAB_EFFECTS="soak capacity temperature short_tau_boost populations linefit_bias blooming ipc"

# The forms, in the order of the docs.
FAMILY_FORMS="soak:capture soak:diffusion capacity:ceiling capacity:langmuir temperature:arrhenius blooming:spill blooming:field ipc:cross4 ipc:aniso8 populations:smooth shape:fill_depth"

# `persist simulate family`'s pinhole option for a row ($1): the forms that couple
# neighbours (blooming, ipc) with the grid of one-pixel pinholes, and so the clean row
# `none+pinholes`; nothing (the seed's own draw) otherwise.
pinhole_args() {
    case $1 in blooming:* | ipc:* | none+pinholes) echo "--pinholes on" ;; *) ;; esac
}
