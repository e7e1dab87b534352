"""Albedo error of a run split by GT material (sRGB after the eval's median scale): share of the
squared error, RMSE and bias per material.  usage: errsplit.py RUN   (spheres data)

Throw-away diagnostics (numpy, PIL) for the shared spheres scene; not part of the build or tests."""
import numpy as np, sys, json
from PIL import Image
run=sys.argv[1]; data='/work/shared/data/spheres'
def lin(a): a=a/255.0; return np.where(a<=0.04045,a/12.92,((a+0.055)/1.055)**2.4)
def enc(x): x=np.clip(x,0,1); return np.where(x<=0.0031308,12.92*x,1.055*x**(1/2.4)-0.055)
G=[];P=[]
for v in range(16):
    gt=np.asarray(Image.open(f'{data}/test_{v:03d}/albedo.png').convert('RGBA')).astype(float)
    pr=np.asarray(Image.open(f'{run}/eval/test_{v:03d}_albedo.png').convert('RGBA')).astype(float)
    m=gt[...,3]>127
    G.append(lin(gt[...,:3])[m]);P.append(lin(pr[...,:3])[m])
G=np.concatenate(G);P=np.concatenate(P)
sc=np.median(G/np.maximum(P,1e-4),0); Ps=P*sc
e=((enc(G)-enc(Ps))**2).sum(1)
print('scale',np.round(sc,3),'PSNR(all masked, approx)',round(-10*np.log10(e.mean()/3),2))
keys=np.round(G*20)/20
u,inv,cnt=np.unique(keys,axis=0,return_inverse=True,return_counts=True)
tot=e.sum()
for k in np.argsort(-cnt)[:9]:
    s=inv.ravel()==k
    print(f'albedo {np.round(G[s].mean(0),2)} pixels {s.mean()*100:5.1f}%  share of SE {e[s].sum()/tot*100:5.1f}%  rmse(enc) {np.sqrt(e[s].mean()/3):.3f}  bias(enc) {np.round((enc(Ps[s])-enc(G[s])).mean(0),3)}')
