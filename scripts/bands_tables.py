"""Print a bands study's train x test band matrices (PSNR, LPIPS, reliance) and KNN per test band from its jobs' results.json.

    python scripts/bands_tables.py sweeps/bands_ray
"""
import json,glob,sys
root=sys.argv[1]
B=['915mhz','1.8ghz','2.4ghz','3ghz']; lab={'915mhz':'915 MHz','1.8ghz':'1.8 GHz','2.4ghz':'2.412 GHz','3ghz':'3 GHz'}
R={}
for f in glob.glob(f'{root}/band=*/results.json'):
    kv=dict(x.split('=') for x in f.split('/')[-2].split(','))
    R[(kv['band'],kv['eval_band'])]=json.load(open(f))
for key,name in (('test/psnr','test PSNR'),('test/lpips','test LPIPS'),('test/reliance_db','neighbour reliance (dB)')):
    print(f'\n**graf-ray-weights**: {name} (rows: train band; columns: test band)\n')
    print('| train \\ test | '+' | '.join(lab[b] for b in B)+' |'); print('|---|'+'---|'*4)
    for a in B:
        row=[]
        for b in B:
            r=R.get((a,b)); v=r['metrics'].get(key) if r else None
            row.append('-' if v is None else (f'{v:.3f}' if 'lpips' in key else f'{v:.2f}'))
        print(f'| {lab[a]} | '+' | '.join(row)+' |')
print('\n**knn** (same neighbours; depends on the test band only): test PSNR / LPIPS\n')
print('| '+' | '.join(lab[b] for b in B)+' |'); print('|'+'---|'*4)
row=[]
for b in B:
    rs=[R[(a,b)] for a in B if (a,b) in R]
    row.append('-' if not rs else f"{rs[0]['baselines']['knn']['metrics']['test/psnr']:.2f} / {rs[0]['baselines']['knn']['metrics']['test/lpips']:.3f}")
print('| '+' | '.join(row)+' |')
secs={k:v['seconds'] for k,v in R.items()}
print('\n<!-- seconds', sorted(secs.values()), '-->')
