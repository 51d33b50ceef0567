"""Fits the Mills ratio M(x) = P(X > x) / phi(x) of a standard normal on [0, 8] by a rational
function P(x) / R(x) of degree 5 over 6 (R(0) = 1, P(0) = sqrt(pi / 2) so that the tail at 0 is
exactly 1/2): least squares in relative error on 4,000 Chebyshev nodes, reweighted by R so that
the linearised problem approaches the rational one. Prints the largest relative error on a grid
4e-5 fine, the smallest value of R there (no pole), and the coefficients that
`crates/mrfmap/src/frames/noise.rs` (MILLS_P, MILLS_R) holds. Needs numpy.

    python3 bench/fit_upper_tail.py
"""
import numpy as np, math
def Q(x): return 0.5*math.erfc(x/math.sqrt(2))
def phi(x): return math.exp(-0.5*x*x)/math.sqrt(2*math.pi)
a,b=0.0,8.0
N=4000
xs=np.array([ (a+b)/2 + (b-a)/2*math.cos(math.pi*(k+0.5)/N) for k in range(N)])
M=np.array([Q(x)/phi(x) for x in xs])
p0=math.sqrt(math.pi/2)
def fit(n,m,iters=30):
    w=np.ones(N)
    for it in range(iters):
        A=np.zeros((N,n+m))
        for i in range(1,n+1): A[:,i-1]=xs**i
        for j in range(1,m+1): A[:,n+j-1]=-M*xs**j
        rhs=M-p0
        sc=1.0/(M*w)
        c,*_=np.linalg.lstsq(A*sc[:,None],rhs*sc,rcond=None)
        p=np.concatenate([[p0],c[:n]]); r=np.concatenate([[1.0],c[n:]])
        w=np.abs(np.polyval(r[::-1],xs))
    return p,r
p, r = fit(5, 6)
xt=np.linspace(0,8,200001)
Mt=np.array([Q(x)/phi(x) for x in xt])
e=np.max(np.abs(np.polyval(p[::-1],xt)/np.polyval(r[::-1],xt)/Mt-1))
print("max rel err", e, "R min", np.min(np.polyval(r[::-1],xt)), "at0", p[0]/r[0]/Mt[0]-1)
print("P", [float.__repr__(float(v)) for v in p])
print("R", [float.__repr__(float(v)) for v in r])
