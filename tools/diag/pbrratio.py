"""Per GT material: mean GT radiance vs the run's PBR radiance (linear, fully covered pixels).
On an oracle run (true materials and light) this is our shading model's error.  usage: pbrratio.py RUN

Throw-away diagnostics (numpy, PIL) for the shared spheres scene; not part of the build or tests."""
import numpy as np, sys
from PIL import Image
run=sys.argv[1]; data='/work/shared/data/spheres'
def lin(a): a=a/255.0; return np.where(a<=0.04045,a/12.92,((a+0.055)/1.055)**2.4)
G=[];P=[];A=[]
for v in range(16):
    gt=np.asarray(Image.open(f'{data}/test_{v:03d}/rgba.png').convert('RGBA')).astype(float)
    al=np.asarray(Image.open(f'{data}/test_{v:03d}/albedo.png').convert('RGBA')).astype(float)
    pr=np.asarray(Image.open(f'{run}/eval/test_{v:03d}_pbr.png').convert('RGBA')).astype(float)
    m=(gt[...,3]>250)
    G.append(lin(gt[...,:3])[m]);P.append(lin(pr[...,:3])[m]);A.append(lin(al[...,:3])[m])
G=np.concatenate(G);P=np.concatenate(P);A=np.concatenate(A)
keys=np.round(A*20)/20
u,inv,cnt=np.unique(keys,axis=0,return_inverse=True,return_counts=True)
for k in np.argsort(-cnt)[:8]:
    s=inv.ravel()==k
    if s.sum()<500: continue
    g=G[s].mean(0);p=P[s].mean(0)
    print(f'albedo {np.round(A[s].mean(0),3)} n={s.sum():6d} GT rad {np.round(g,4)} ours {np.round(p,4)} GT/ours {np.round(g/p,2)}  GT/albedo {np.round(g/A[s].mean(0),3)} ours/albedo {np.round(p/A[s].mean(0),3)}')
