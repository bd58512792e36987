# The truth's log-likelihood per innovation above the best Gaussian a sample fits (its own variance), for the
# x1 Student-t (2.19 dof) and the x1 two-normal mixture (10% at 10x), over 200 samples of 600 innovations and 3 of
# 100,000. Standard library only: python3 results/heavy-tail-distance/distance_at_sample_size.py
import random, statistics as S
from tails import t_draw, t_logpdf, mix_logpdf, gap_to_sample_gaussian
random.seed(3)
for N in (600, 100000):
    for label,draw,logp in [('t(2.19)',lambda: t_draw(2.19),lambda x: t_logpdf(x,2.19)),('mixture 10% at 10x',lambda: random.gauss(0,10.0 if random.random()<0.1 else 1.0),lambda x: mix_logpdf(x,0.1,10.0))]:
        reps=200 if N==600 else 3
        gaps=[]
        for _ in range(reps):
            gaps.append(gap_to_sample_gaussian([draw() for _ in range(N)], logp))
        print(f"N={N} {label}: truth minus the sample's best Gaussian, per innovation: median {S.median(gaps):.3f}, IQR {S.quantiles(gaps,n=4)[0]:.3f}-{S.quantiles(gaps,n=4)[2]:.3f}" if reps>3 else f"N={N} {label}: {[round(g,3) for g in gaps]}")
