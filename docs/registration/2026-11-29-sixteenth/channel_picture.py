# Draws red_channel.jpg: a photo crop, its grey and its red channel over the ROI (1-99 % range),
# from phantom sets made under /tmp/nb (cortexfuse phantom ev8 --n 8 --seed 101, chris --seed 303).
import cv2, json, glob, numpy as np
rows=[]
for st,c,label in [('ev8','0007','ev8 0007: a film of blood'),('ev8','0003','ev8 0003: sulci, pools'),('chris','0001','chris 0001: blood in sulci')]:
    cd=f'/tmp/nb/{st}/case_{c}'; im=cv2.imread(glob.glob(cd+'/photo.*')[0])
    pts=np.array(json.load(open(cd+'/roi.json'))['points'],np.int32)
    x,y,w,h=cv2.boundingRect(pts); m=np.zeros(im.shape[:2],np.uint8); cv2.fillPoly(m,[pts],255)
    crop=im[y:y+h,x:x+w]; mc=m[y:y+h,x:x+w]
    def norm(ch):
        v=ch[mc>0].astype(np.float32); lo,hi=np.percentile(v,1),np.percentile(v,99)
        o=np.clip((ch.astype(np.float32)-lo)/(hi-lo+1e-6),0,1)*255; o[mc==0]=40; return cv2.cvtColor(o.astype(np.uint8),cv2.COLOR_GRAY2BGR)
    b,g,r=[crop[...,i].astype(np.float32) for i in range(3)]
    grey=(0.299*r+0.587*g+0.114*b)
    tiles=[crop.copy(), norm(grey), norm(r)]
    H=300; tiles=[cv2.resize(t,(int(t.shape[1]*H/t.shape[0]),H),interpolation=cv2.INTER_AREA) for t in tiles]
    for t,txt in zip(tiles,[label,'grey channel (before)','red channel (now)']):
        cv2.rectangle(t,(0,0),(len(txt)*9+8,22),(0,0,0),-1); cv2.putText(t,txt,(4,16),cv2.FONT_HERSHEY_SIMPLEX,0.5,(255,255,255),1,cv2.LINE_AA)
    row=np.hstack([np.pad(t,((3,3),(3,3),(0,0)),constant_values=255) for t in tiles]); rows.append(row)
W=max(r.shape[1] for r in rows); rows=[np.pad(r,((0,0),(0,W-r.shape[1]),(0,0)),constant_values=255) for r in rows]
cv2.imwrite('/work/main/docs/registration/2026-11-29-sixteenth/red_channel.jpg',np.vstack(rows),[cv2.IMWRITE_JPEG_QUALITY,85])
