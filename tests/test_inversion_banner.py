"""The red banner of a flagged 2D inversion picture (femreg.plot.plot_inversion): every flag's gist, the
parenthesised detail left to the message, so a long first flag does not hide the others."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

from femreg.plot import flag_gist  # noqa: E402

MISFIT = ("the misfit 0.0738 stays well above the noise level of registered fields (limit 0.02, in units of the "
          "model's squared displacement change across one element): the plane-stress model does not explain the data")
REGIONS = ("15 region(s) of 339 mm^2 (45 % of the inner area; 5.66 mm^2 at mu 37.4 x the background, |e_xx| 2.23 x) "
           "whose modulus step the axial strain does not show, and the image is not a few regions (the region refit "
           "was not applied): its levels are the regulariser's (e.g. at a low SNR); the contrast is not reliable")


def test_flag_gist_drops_the_parenthesised_detail():
    assert flag_gist(MISFIT) == ("the misfit 0.0738 stays well above the noise level of registered fields: the "
                                 "plane-stress model does not explain the data")
    g = flag_gist(REGIONS)
    assert g.startswith("15 regions of 339 mm^2 whose modulus step") and g.endswith("the contrast is not reliable")
    assert "(" not in g and ")" not in g and "37.4" not in g
    assert flag_gist("beta (a (nested) note) at the edge") == "beta at the edge"


def test_the_banner_names_every_flag(tmp_path):
    from test_inversion import REGION, solution

    from femreg.inversion import invert

    res = invert(solution("plane-stress", 40.0).displacement, region=REGION, element_size=3.0, beta=1e-3,
                 uncertainty=False)
    res.success, res.flags = False, [MISFIT, REGIONS]
    res.message = "FLAGGED: " + "; ".join(res.flags)
    fig = res.plot(tmp_path / "mu.png")
    text = " ".join(fig._suptitle.get_text().split())
    assert text.startswith("INVERSION FLAGGED: the misfit 0.0738")
    # the second flag's conclusion, which the three-line cut of the whole message lost
    assert "the contrast is not reliable" in text and "plane-stress model does not explain the data" in text
