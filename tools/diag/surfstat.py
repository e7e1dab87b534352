"""Surfel census of a run on a shared scene: per README object, surfels by signed distance to its surface
(deep inside / inside / surface / outside), their mean opacity and learned albedo.
usage: surfstat.py RUN [DATA]

Throw-away diagnostics (numpy, PIL) for the shared spheres scene; not part of the build or tests."""
import numpy as np, sys, json
run=sys.argv[1]; data=sys.argv[2] if len(sys.argv)>2 else '/work/shared/data/spheres'
raw=open(f'{run}/point_cloud.ply','rb').read()
hdr_end=raw.index(b'end_header\n')+len(b'end_header\n')
hdr=raw[:hdr_end].decode().splitlines()
props=[l.split()[2] for l in hdr if l.startswith('property')]
n=int([l for l in hdr if l.startswith('element vertex')][0].split()[2])
a=np.frombuffer(raw[hdr_end:],dtype='<f4',count=n*len(props)).reshape(n,len(props))
P={p:a[:,i] for i,p in enumerate(props)}
xyz=np.stack([P['x'],P['y'],P['z']],1)
sig=lambda x:1/(1+np.exp(-x))
alb=0.03+0.77*sig(np.stack([P['albedo_0'],P['albedo_1'],P['albedo_2']],1))
op=sig(P['opacity'])
rd=json.load(open(f'{data}/README.json'))
objs=rd['objects']
d=[]
for o in objs:
    loc=np.array(o['location'])
    if o['type']=='uv_sphere':
        d.append(np.linalg.norm(xyz-loc,axis=1)-o['params']['radius'])
    elif o['type']=='cylinder':
        r=o['params']['radius']; h=o['params']['depth']/2
        q=xyz-loc; dr=np.hypot(q[:,0],q[:,1])-r; dz=np.abs(q[:,2])-h
        d.append(np.minimum(np.maximum(dr,dz),0)+np.hypot(np.maximum(dr,0),np.maximum(dz,0)))
    else:
        d.append(np.full(n,1e9))
d=np.array(d); k=np.argmin(np.abs(d),0); dist=d[k,np.arange(n)]
for j,o in enumerate(objs):
    m=rd['materials'][o['material']] if 'materials' in rd else None
    sel=k==j
    print(o['object'], 'n',sel.sum(), 'GT', m.get('base_color') if m else '')
    for lo,hi,name in [(-9,-0.03,'deep in'),(-0.03,-0.005,'in'),(-0.005,0.005,'surface'),(0.005,9,'out')]:
        s=sel&(dist>=lo)&(dist<hi)
        if s.sum()==0: continue
        w=op[s]
        print(f'   {name:8s} n={s.sum():5d} opac {w.mean():.2f} albedo mean {np.round(alb[s].mean(0),3)} opac-weighted {np.round((alb[s]*w[:,None]).sum(0)/w.sum(),3)}')
print('distance histogram (mm) per sphere:')
for j,o in enumerate(objs):
    sel=k==j
    h,e=np.histogram(dist[sel]*1000,bins=[-400,-200,-100,-50,-30,-20,-10,-5,0,5,10,20,50,400])
    print(o['object'][:10], ' '.join(f'{int(a)}..{int(b)}:{c}' for a,b,c in zip(e[:-1],e[1:],h)))
