# How far each heavy-tail family is from the Gaussian a sample of 600 innovations fits (its own variance),
# along each family's own scale: the Student-t over its degrees of freedom (below 2 its variance is infinite,
# which the generator refuses) and the two-normal mixture (10% wide) over its sd ratio (x0.5, x1 and x2 of the
# ladder are 5.5x, 10x and 19x). The truth's log-likelihood per innovation above that Gaussian, median and IQR
# over 200 samples. It shows which mixture strength a Student-t matches on what a sample holds, and that no
# finite-variance t reaches the x1 mixture. Standard library only:
#     python3 results/heavy-tail-distance/sample_distance_ladder.py
import random
import statistics as S

from tails import gap_to_sample_gaussian, mix_logpdf, t_draw, t_logpdf

random.seed(5)
N, REPS = 600, 200


def distance(draw, logp):
    gaps = [gap_to_sample_gaussian([draw() for _ in range(N)], logp) for _ in range(REPS)]
    q = S.quantiles(gaps, n=4)
    return f"median {S.median(gaps):.3f}, IQR {q[0]:.3f}-{q[2]:.3f}"


for nu in (1.0, 1.5, 2.01, 2.06, 2.19, 2.56, 3.0, 4.0, 6.0):
    note = {2.06: " (x2)", 2.19: " (x1)", 2.56: " (x0.5)"}.get(nu, "") + (" (infinite variance)" if nu <= 2 else "")
    print(f"Student-t, {nu} dof{note}: {distance(lambda: t_draw(nu), lambda x: t_logpdf(x, nu))}")
for k in (3.0, 4.0, 5.5, 7.0, 10.0, 19.0):
    note = {5.5: " (x0.5)", 10.0: " (x1)", 19.0: " (x2)"}.get(k, "")
    print(f"mixture, 10% at {k}x{note}: {distance(lambda: random.gauss(0, k if random.random() < 0.1 else 1.0), lambda x: mix_logpdf(x, 0.1, k))}")
