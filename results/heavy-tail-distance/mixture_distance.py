# The two-normal mixture's log-likelihood per innovation above the best Gaussian, at the ladder's three strengths.
# Standard library only: python3 results/heavy-tail-distance/mixture_distance.py
import random, math
from tails import n_logpdf, mix_logpdf
random.seed(2)
for (p,k,label) in [(0.1,10.0,'x1'),(0.1,5.5,'x0.5'),(0.1,19.0,'x2')]:
    N=200000
    xs=[random.gauss(0,k if random.random()<p else 1.0) for _ in range(N)]
    lt=sum(mix_logpdf(x,p,k) for x in xs)/N
    s=math.sqrt(sum(x*x for x in xs)/N); lg=sum(n_logpdf(x,s) for x in xs)/N
    print(label, f"mixture {p:.0%} at {k}x: truth {lt:.4f}, best Gaussian {lg:.4f}: {lt-lg:.3f} nats per innovation")
