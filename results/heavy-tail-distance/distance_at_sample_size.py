# The truth's log-likelihood per innovation above the best Gaussian a sample fits (its own variance), for the
# x1 Student-t (2.19 dof) and the x1 two-normal mixture (10% at 10x), over 200 samples of 600 innovations and 3 of
# 100,000. Standard library only: python3 results/heavy-tail-distance/distance_at_sample_size.py
import random, math, statistics as S
random.seed(3)
def t_draw(nu):
    z=random.gauss(0,1); c=random.gammavariate(nu/2,2.0); return z/math.sqrt(c/nu)
def t_logpdf(x,nu): return math.lgamma((nu+1)/2)-math.lgamma(nu/2)-0.5*math.log(nu*math.pi)-(nu+1)/2*math.log1p(x*x/nu)
def n_logpdf(x,s): return -0.5*math.log(2*math.pi*s*s)-x*x/(2*s*s)
def mix_logpdf(x,p,k):
    l1=math.log(1-p)+n_logpdf(x,1.0); l2=math.log(p)+n_logpdf(x,k); m=max(l1,l2); return m+math.log(math.exp(l1-m)+math.exp(l2-m))
for N in (600, 100000):
    for label,draw,logp in [('t(2.19)',lambda: t_draw(2.19),lambda x: t_logpdf(x,2.19)),('mixture 10% at 10x',lambda: random.gauss(0,10.0 if random.random()<0.1 else 1.0),lambda x: mix_logpdf(x,0.1,10.0))]:
        reps=200 if N==600 else 3
        gaps=[]
        for _ in range(reps):
            xs=[draw() for _ in range(N)]
            s=math.sqrt(sum(x*x for x in xs)/N)
            gaps.append(sum(logp(x)-n_logpdf(x,s) for x in xs)/N)
        print(f"N={N} {label}: truth minus the sample's best Gaussian, per innovation: median {S.median(gaps):.3f}, IQR {S.quantiles(gaps,n=4)[0]:.3f}-{S.quantiles(gaps,n=4)[2]:.3f}" if reps>3 else f"N={N} {label}: {[round(g,3) for g in gaps]}")
