"""Copy a run with each surfel's albedo replaced by an indicator (R deep inside an object, G surface
band, B outside), so that `radiogs render --mode albedo` shows which surfels a pixel blends.
usage: indicator.py RUN OUT

Throw-away diagnostics (numpy, PIL) for the shared spheres scene; not part of the build or tests."""
import numpy as np, sys, json, shutil, os
exec(open(os.path.join(os.path.dirname(os.path.abspath(__file__)),'surfstat.py')).read().split("for j,o in enumerate(objs):\n    m=")[0].replace("run=sys.argv[1]; data=sys.argv[2] if len(sys.argv)>2 else '/work/shared/data/spheres'","run=sys.argv[1]; data='/work/shared/data/spheres'"))
out=sys.argv[2]
os.makedirs(out,exist_ok=True)
for f in os.listdir(run):
    if os.path.isfile(f'{run}/{f}') and f!='point_cloud.ply': shutil.copy(f'{run}/{f}',out)
ind=np.zeros((n,3))
ind[:,0]=dist<-0.03; ind[:,1]=(dist>=-0.03)&(dist<0.01); ind[:,2]=dist>=0.01
val=0.03+0.77*np.clip(ind,0.001,0.999)
lg=np.log((val-0.03)/0.77/(1-(val-0.03)/0.77))
b=a.copy()
for c in range(3): b[:,props.index(f'albedo_{c}')]=lg[:,c]
open(f'{out}/point_cloud.ply','wb').write(raw[:hdr_end]+b.astype('<f4').tobytes())
